"""The forward model: scan geometry, the Gaussians, their exact line integrals (projector) and
their voxelisation. Imports nothing from the rest of mi_grg."""
