"""Evaluation metrics: trajectory error (`trajectory`: ATE, RPE, checked against evo), image
quality (`images`: PSNR, SSIM, depth L1, masked) and the perceptual distance (`lpips`: LPIPS
v0.1, AlexNet)."""
