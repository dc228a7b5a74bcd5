"""Diffuse reflectivity of a catalog type at the sensor's wavelength (SPEC section 8).

A type may carry its own value (``catalog add --reflectivity``); otherwise its category's default
below. The defaults are round figures for the near infrared (1.0-1.6 um), where paints change
little between 1064 and 1550 nm: white gloss paints reflect about 0.6-0.8 and grey
low-visibility military paints about 0.1-0.2 diffusely there (ECOSTRESS / ASTER spectral
library, Baldridge et al., Remote Sens. Environ. 2009, man-made materials: paints), grey and
white plastics about 0.2-0.5. Weathering, metal and glass lower the airliners' whole-airframe
value below a clean white panel's, hence 0.6. Each is an assumption to replace with a
measurement of the type when one exists.
"""

from __future__ import annotations

import math

from ..errors import InputError

CATEGORY_REFLECTIVITY = {
    "airliner_narrowbody": 0.6,  # white-painted fuselage, painted or bare-metal wings
    "airliner_widebody": 0.6,
    "regional_jet": 0.6,
    "turboprop": 0.6,
    "business_jet": 0.6,  # composite or metal airframes, painted white
    "light_GA": 0.6,  # white paint
    "military_transport": 0.15,  # grey low-visibility paint
    "fighter": 0.15,  # grey low-visibility paint
    "helicopter": 0.15,  # military olive / grey (the catalog's are military-heavy)
    "fixed_wing_drone": 0.3,  # grey / white composite and plastic
    "multirotor_drone": 0.3,  # grey plastic (the catalog's DJI-class multirotors)
}
DEFAULT_REFLECTIVITY = 0.3  # a category not listed above: a middle grey


def check_reflectivity(value, name: str = "reflectivity") -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a number in (0, 1], got {value!r}") from exc
    if not math.isfinite(v) or not 0.0 < v <= 1.0:
        raise InputError(f"{name} must be in (0, 1] (a diffuse reflectance), got {value!r}")
    return v


def reflectivity_of(aircraft_type) -> float:
    """The type's own reflectivity when it has one, else its category's default."""
    own = getattr(aircraft_type, "reflectivity", None)
    if own is not None and own == own:
        return check_reflectivity(own, f"reflectivity of {aircraft_type.name!r}")
    return CATEGORY_REFLECTIVITY.get(getattr(aircraft_type, "category", ""),
                                     DEFAULT_REFLECTIVITY)
