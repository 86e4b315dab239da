"""The avatar: canonical Gaussians -> corrector -> deformer -> rasterizer, with Gaussian initialisation, the corrector
MLP, positional encoding, the composite loss and optimizer surgery. Imports rig, splat, image, interfaces and core."""
