"""Network building blocks for range-image diffusion (ring convolutions, UNet, MoST)."""
