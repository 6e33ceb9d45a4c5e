"""Voxel-grid baselines: the Joseph projector, FDK, SART / OS-SART and ASD-POCS."""
