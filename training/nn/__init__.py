"""Dense 2D networks: deformable conv, RGFD, noise adapter, light denoiser, R2LDM U-Net."""
