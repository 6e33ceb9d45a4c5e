"""The cross-check's statistics: Monte Carlo transmittance (the mean of ``spp`` 0/1
samples per pixel) against the exact one, per view and per pixel."""
from __future__ import annotations

import math

import numpy as np

CONFIDENCE = 0.999
#: What the standard errors assume, verified on every render (``_render_checked``).


def compare(mc: np.ndarray, ref_t: np.ndarray, spp: int) -> dict:
    """Error statistics of Monte Carlo transmittance ``mc`` against the exact ``ref_t``.

    Standard errors are the Bernoulli ones of the reference, sqrt(T (1 - T) / spp) per
    pixel; pixels with T = 1 (rays missing the object, error exactly 0) carry no
    information and are left out of the z statistics."""
    err = mc - ref_t
    se = np.sqrt(np.clip(ref_t * (1 - ref_t), 0, None) / spp)
    used = se > 0
    n = max(int(used.sum()), 1)
    se_mean = math.sqrt(float(np.sum(se[used] ** 2))) / n   # standard error of the mean error
    z = err[used] / se[used]
    return {"mean_error": float(err.mean()), "mean_abs_error": float(np.abs(err).mean()),
            "rms_error": float(np.sqrt(np.mean(err ** 2))),
            "mean_standard_error": float(se[used].mean()) if used.any() else 0.0,
            "standard_error_of_mean": se_mean,
            "z_mean": float(err[used].mean() / se_mean) if used.any() and se_mean > 0 else 0.0,
            "z_rms": float(np.sqrt(np.mean(z ** 2))) if used.any() else 0.0,
            "max_abs_z": float(np.abs(z).max()) if used.any() else 0.0,
            "pixels_used": int(used.sum())}


def view_statistics(mc: np.ndarray, ref: np.ndarray, spp: int,
                    confidence: float = CONFIDENCE) -> list:
    """Per view: the transmittance error of ``mc`` [view, v, u] (the mean of ``spp`` 0/1
    samples per pixel) against the exact ``ref``, and a pass/fail at ``confidence``.

    A view passes when (a) its mean error, divided by its standard error (the binomial
    sqrt(T (1 - T) / spp) per pixel, T = reference), is within the two-sided normal
    quantile of ``confidence`` (a bias test), and (b) no pixel's count is improbable:
    the smallest exact two-sided binomial p-value is >= (1 - confidence) / pixels
    (Bonferroni; exact rather than normal because at small spp or T near 1 a single
    absorbed sample is many normal sigmas). Pixels with T = 1 (rays that miss the object)
    enter (b) only: any absorbed sample there fails the view."""
    from scipy.stats import binom, norm
    alpha = 1.0 - float(confidence)
    z_crit = float(norm.ppf(1.0 - alpha / 2))
    out = []
    for k in range(mc.shape[0]):
        m, t = np.asarray(mc[k], np.float64), np.clip(np.asarray(ref[k], np.float64), 0, 1)
        err = m - t
        var = t * (1 - t) / spp
        used = var > 0
        n_used = int(used.sum())
        se_mean = math.sqrt(float(var[used].sum())) / n_used if n_used else 0.0
        z = float(err[used].mean() / se_mean) if se_mean > 0 else 0.0
        count = np.rint(m * spp)
        p = np.minimum(1.0, 2 * np.minimum(binom.cdf(count, spp, t),
                                           binom.sf(count - 1, spp, t)))
        p_min = float(p.min())
        out.append({
            "rms_difference": float(np.sqrt(np.mean(err ** 2))),
            "max_abs_difference": float(np.abs(err).max()),
            "mean_difference": float(err.mean()),
            # what the RMS difference should be at this spp if volpath and reference agree
            "expected_rms_standard_error": float(np.sqrt(var.mean())),
            "standard_error_of_mean_difference": se_mean,
            "z": z,
            "z_rms": float(np.sqrt(np.mean(err[used] ** 2 / var[used]))) if n_used else 0.0,
            "min_pixel_p_value": p_min,
            "pixels": int(m.size), "pixels_informative": n_used,
            "pass": bool(abs(z) <= z_crit and p_min >= alpha / m.size)})
    return out


def binomial_z(mc: np.ndarray, ref: np.ndarray, spp: int) -> np.ndarray:
    """Per pixel, (volpath - reference) / standard error as a binomial z-score: the normal
    quantile of the mid-p value P(K < k) + P(K = k) / 2, K ~ Binomial(spp, T), k the
    pixel's count. Where spp T (1 - T) is large this is (mc - T) / sqrt(T (1 - T) / spp);
    where it is small (T near 0 or 1) it stays honest: one absorbed sample at T = 0.999
    and 256 spp is z = -1.1, not the -8 of the normal formula. T = 1 with no absorbed
    sample is 0; an impossible count (e.g. an absorbed sample at T = 1) is -inf / +inf."""
    from scipy.stats import binom, norm
    t = np.clip(np.asarray(ref, np.float64), 0, 1)
    k = np.rint(np.asarray(mc, np.float64) * spp)
    mid = binom.cdf(k - 1, spp, t) + 0.5 * binom.pmf(k, spp, t)
    return norm.ppf(mid)
