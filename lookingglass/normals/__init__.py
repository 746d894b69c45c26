"""Normal reconstruction (paper Sec. 3.1): rendering layer, networks, cost volume, latent optimization."""
