"""splatrig: animatable 3D Gaussian avatars from multi-view video.

`framework` is the engine (registries, types, training loop); `plugins` holds every interchangeable part.
"""

__version__ = "0.2.0"

from framework import config_resolvers as _config_resolvers  # noqa: E402,F401  (registers ${scaled:...}, ${steps:...})
from framework import config_schema as _config_schema  # noqa: E402

_config_schema.register()  # `schema_train`, the types conf/train.yaml is composed onto
