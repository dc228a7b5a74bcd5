"""The link budget (SPEC section 8): signal photo-electrons per pulse from each sub-ray of a
cell, the atmosphere's transmission, and the noise counts per range bin."""

from __future__ import annotations

import math

import numpy as np

from .params import SensorParams

PLANCK_J_S = 6.62607015e-34  # exact (SI 2019)
LIGHT_M_S = 299_792_458.0  # exact (SI)
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))  # 2.355: a Gaussian's FWHM / sigma


def kim_extinction_per_m(visibility_km: float, wavelength_nm: float) -> float:
    """Aerosol extinction coefficient sigma_ext (1/m) from the visibility, by Kim's model
    (Kim, McArthur, Korevaar, SPIE 4214, 2001): sigma = 3.912 / V (lambda / 550 nm)^-q with
    q = 1.6 (V > 50 km), 1.3 (6-50 km), 0.16 V + 0.34 (1-6 km), V - 0.5 (0.5-1 km), 0 below."""
    v = float(visibility_km)
    if v > 50.0:
        q = 1.6
    elif v > 6.0:
        q = 1.3
    elif v > 1.0:
        q = 0.16 * v + 0.34
    elif v > 0.5:
        q = v - 0.5
    else:
        q = 0.0
    return 3.912 / (v * 1e3) * (wavelength_nm / 550.0) ** (-q)


def transmission(range_m, sensor: SensorParams):
    """One-way atmospheric transmission T(r) = exp(-sigma_ext r)."""
    sigma = kim_extinction_per_m(sensor.visibility_km, sensor.wavelength_nm)
    return np.exp(-sigma * np.asarray(range_m, dtype=np.float64))


def photons_per_joule(wavelength_nm: float) -> float:
    return wavelength_nm * 1e-9 / (PLANCK_J_S * LIGHT_M_S)


def signal_photoelectrons(range_m, cos_incidence, reflectivity, sensor: SensorParams,
                          sub_rays: int):
    """Mean signal photo-electrons per pulse from each sub-ray (SPEC section 8):
    N_j = (E lambda / h c) eta_o eta_d T(r_j)^2 rho cos_j D^2 / (4 r_j^2) / K^2, a Lambertian
    target filling the sub-ray's share (1 / K^2) of a cell lit by E = pulse_energy /
    cells_per_pulse."""
    r = np.asarray(range_m, dtype=np.float64)
    energy = sensor.pulse_energy_j / sensor.cells_per_pulse
    scale = (energy * photons_per_joule(sensor.wavelength_nm) * sensor.optics_efficiency
             * sensor.detector_efficiency * sensor.aperture_m**2 / 4.0 / sub_rays)
    return (scale * transmission(r, sensor) ** 2 * np.asarray(reflectivity)
            * np.clip(np.asarray(cos_incidence, dtype=np.float64), 0.0, 1.0) / r**2)


def timing_sigma_s(sensor: SensorParams) -> float:
    """sigma_t = sqrt((pulse FWHM / 2.355)^2 + jitter^2), seconds."""
    return math.hypot(sensor.pulse_fwhm_ps / FWHM_PER_SIGMA, sensor.jitter_ps) * 1e-12


def range_sigma_m(sensor: SensorParams) -> float:
    """The spread of a return's range: c sigma_t / 2."""
    return LIGHT_M_S * timing_sigma_s(sensor) / 2.0


def bin_seconds(r_r_m: float) -> float:
    """A range bin of R_r metres lasts 2 R_r / c seconds."""
    return 2.0 * r_r_m / LIGHT_M_S


def noise_per_bin(sensor: SensorParams, r_r_m: float) -> float:
    """Mean noise counts per range bin per pulse: (background + dark) x 2 R_r / c."""
    return sensor.noise_hz * bin_seconds(r_r_m)


def sky_background_hz(radiance_w_m2_sr_nm: float, solid_angle_sr: float, aperture_m: float,
                      filter_nm: float, optics_efficiency: float, detector_efficiency: float,
                      wavelength_nm: float) -> float:
    """Detector counts per second from a sky of spectral radiance L behind the target:
    L Omega (pi D^2 / 4) d_lambda eta_o, in photons, times eta_d (how the day presets'
    background_hz are derived, each preset file says from what)."""
    watts = (radiance_w_m2_sr_nm * solid_angle_sr * math.pi * aperture_m**2 / 4.0 * filter_nm
             * optics_efficiency)
    return watts * photons_per_joule(wavelength_nm) * detector_efficiency


def erf(x):
    """The error function, vectorised, to ~1e-7 (Abramowitz & Stegun 7.1.26): numpy has none
    and the core must not need scipy."""
    x = np.asarray(x, dtype=np.float64)
    s = np.sign(x)
    a = np.abs(x)
    t = 1.0 / (1.0 + 0.3275911 * a)
    y = 1.0 - (((((1.061405429 * t - 1.453152027) * t) + 1.421413741) * t - 0.284496736) * t
               + 0.254829592) * t * np.exp(-a * a)
    return s * y


def normal_cdf(x):
    return 0.5 * (1.0 + erf(np.asarray(x) / math.sqrt(2.0)))
