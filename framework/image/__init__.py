"""Image-space measures shared by losses and metrics, in torch: the training SSIM map (its compiled twin is
`framework.kernels.ssim`), the LPIPS network and its shipped weights. Imports torch, kornia and the core modules
only."""
