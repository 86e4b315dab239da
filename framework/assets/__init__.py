"""Files shipped with the package: `demo_avatar.ckpt`, the avatar `ckpt=demo` loads (tools/make_demo_avatar.py)."""
