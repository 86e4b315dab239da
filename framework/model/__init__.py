"""The avatar: canonical Gaussians -> corrector -> deformer -> rasterizer, with Gaussian initialisation, the corrector
MLP, positional encoding, the composite loss and optimizer surgery. Imports kernels (where the model's execution
compiles), rig, splat, image, interfaces and core."""
