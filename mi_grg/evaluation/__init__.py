"""Scoring and checking a reconstruction: PSNR / SSIM, slice plots and the Mitsuba
path-traced cross-check."""
