"""Evaluation metrics: trajectory error (`trajectory`: ATE, RPE, checked against evo) and image
quality (`images`: PSNR, SSIM, depth L1, masked)."""
