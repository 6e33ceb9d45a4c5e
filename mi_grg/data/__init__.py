"""Scans as data: the Case type, the R2-Gaussian layout on disk, scene XML, phantoms and
simulated noisy scans."""
