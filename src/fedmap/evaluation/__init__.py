"""Map quality (PSNR, SSIM) and path-planning evaluation (A* path F1)."""
