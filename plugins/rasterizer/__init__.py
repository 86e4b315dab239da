"""Built-in rasterizer components; importing this package registers every module in it."""

from framework.plugins import import_submodules

import_submodules(__name__)
