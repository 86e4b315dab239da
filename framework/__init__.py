"""splatrig: animatable 3D Gaussian avatars from multi-view video.

`framework` is the engine (registries, types, training loop); `plugins` holds every interchangeable part.
"""

__version__ = "0.1.0"
