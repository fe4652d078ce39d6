"""Attenuation coefficient beta per camera channel for the ten Jerlov water types (eqs. 1-4), from `jerlov`.

Which coefficient: the downwelling diffuse attenuation Kd of Jerlov (1976) (`jerlov.water(name, "jerlov1976")`).
It is the only table in the package that covers all ten types over the whole visible range without a gap
(Solonenko & Mobley's a and b are missing for 5C above 600 nm), it is what UWCNN-style synthesis uses for
"Jerlov beta", and it is the effective attenuation of light that reaches the camera after forward scattering
(the beam attenuation c = a + b counts forward-scattered light as lost, which overstates the loss of a
blurred-but-present image signal).

Which wavelengths stand for R, G, B: none single; each channel is a band average of Kd weighted by a
camera-like spectral response S_c(lambda) times daylight D65(lambda) (the light a white target returns):

    beta_c = sum_lambda S_c Kd D65 / sum_lambda S_c D65,   lambda = 400..700 nm every 1 nm.

S_c is the ideal sRGB camera: the CIE 1931 colour matching functions mapped to linear sRGB primaries
(`jerlov.colour.XYZ_TO_LINEAR_SRGB`) with the negative lobes clipped, peaking at 605 / 539 / 445 nm. A camera
records a band, not a line, and this is the band an sRGB image claims to encode. The band-average is the
small-distance limit of the effective channel attenuation -ln(sum S E e^{-Kd d} / sum S E) / d (Akkaynak et al.
2017); it keeps eq. 1 per-channel exponential as the paper writes it. 400-700 nm is Jerlov's printed range
(values outside it are extrapolated by the dataset) and covers > 99.6 % of each channel's weight.
"""

from __future__ import annotations

import warnings
from functools import cache, lru_cache

import numpy as np

from ruslam.errors import InputError

WATER_TYPES: tuple[str, ...] = ("I", "IA", "IB", "II", "III", "1C", "3C", "5C", "7C", "9C")
KD_SOURCE = "jerlov1976"
BAND_NM = (400.0, 700.0)


def check_water_type(name: str) -> str:
    """Return ``name`` if it is a Jerlov type, else raise one sentence listing the valid names."""
    if name not in WATER_TYPES:
        raise InputError(f"Unknown Jerlov water type {name!r}; expected one of {', '.join(WATER_TYPES)}.")
    return name


@lru_cache(maxsize=1)
def camera_response() -> tuple[np.ndarray, np.ndarray]:
    """(wavelengths [n] nm, weights [n,3] for R,G,B): ideal sRGB camera response times D65, 400-700 nm."""
    import jerlov
    from jerlov.colour import XYZ_TO_LINEAR_SRGB

    wl, cmf = jerlov.cie_1931_cmf()
    keep = (wl >= BAND_NM[0]) & (wl <= BAND_NM[1])
    wl, cmf = wl[keep], cmf[keep]
    response = np.clip(cmf @ np.asarray(XYZ_TO_LINEAR_SRGB).T, 0.0, None)
    d65_wl, d65 = jerlov.d65()
    weights = response * np.interp(wl, d65_wl, d65)[:, None]
    weights.setflags(write=False)
    return wl, weights


@cache
def kd_spectrum(name: str) -> np.ndarray:
    """Jerlov (1976) Kd [n] in 1/m on the wavelengths of `camera_response`."""
    import jerlov

    wl, _ = camera_response()
    with warnings.catch_warnings():  # 400-700 nm rests on printed or interpolated values only
        warnings.simplefilter("ignore")
        kd = np.asarray(jerlov.water(check_water_type(name), source=KD_SOURCE).kd(wl), dtype=np.float64)
    if not np.all(np.isfinite(kd)):
        raise RuntimeError(f"jerlov returned non-finite Kd for Jerlov {name} in {BAND_NM} nm.")
    kd.setflags(write=False)
    return kd


def beta_rgb(name: str) -> np.ndarray:
    """Attenuation coefficient [3] (R, G, B) in 1/m of Jerlov water type ``name`` (band-averaged Kd)."""
    _, weights = camera_response()
    kd = kd_spectrum(name)
    return (weights * kd[:, None]).sum(0) / weights.sum(0)
