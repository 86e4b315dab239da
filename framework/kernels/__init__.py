"""The compiled CPU kernels (numba), all behind this one boundary: rasterizer projection and compositing, SH colours,
skinning, blend-weight lookup, positional encoding, SSIM and their hand-written backward passes, each the twin of a
torch function in rig/, splat/, image/ or model/ (the same rules; tests compare the two). Imports rig, splat, image
(their constants and types) and core; nothing below imports it: model/ and plugins/ call a kernel when the model's
`framework.execution.Execution` says it takes the tensors."""
