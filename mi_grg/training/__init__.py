"""R2-Gaussian / GR-Gaussian training: configuration, initialisation, the kNN graph,
densification, the optimiser, losses, early stopping and the training loop."""
