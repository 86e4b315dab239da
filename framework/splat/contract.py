"""The numbers of the rasterizer contract (its rules are written out in `framework.interfaces.rasterizer`).

They live here, below the interfaces, because the splatting math (`projection`, `jax_raster`) applies them too: the
interface and the math read one definition, and no arrow runs from `splat/` back up to `interfaces/`.
"""

import math

NEAR_PLANE = 0.01  # a Gaussian with camera-space z <= near is culled
FAR_PLANE = 1e10  # ... and one with z >= far
EPS2D = 0.3  # px^2 added to the 2D covariance diagonal (low-pass filter)
ALPHA_MIN = 1.0 / 255.0  # a (Gaussian, pixel) pair contributes only from this alpha up
ALPHA_MAX = 0.999  # alpha is clamped to this
TRANSMITTANCE_MIN = 1e-4  # a pixel is finished when its transmittance would fall to this
LOG_T_MIN = math.log(TRANSMITTANCE_MIN)  # the same test on a running sum of log(1 - alpha)
BOX_MARGIN = 1e-3  # px added to a float screen box so rounding never drops a pixel right on its edge
