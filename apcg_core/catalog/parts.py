"""The tables the catalog builders read (data only; the drawing is in ``builders``).

``types.csv`` describes each type in words (``wing_position``, ``tail_type``,
``engine_placement``, ``propulsion``); the tables here say what each of those phrases means for
the parts, and what each category looks like. The builders read a type through these tables and
its numbers only: they never look at its name or search its free text. A new row of
``types.csv`` that reuses known phrases needs nothing here; a new phrase needs one entry (the
builders refuse an unknown one, naming it and the accepted ones). The few types whose listed
facts alone would draw them wrongly have an entry in :data:`TYPE_OVERRIDES`.

Lengths are fractions of the listed length (L) or of the fuselage diameter (D), as noted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..lidar import DEG

# --- categories ------------------------------------------------------------------------------

# Which builder draws each category (``builders.BUILDERS``).
BUILDER = {
    "airliner_narrowbody": "fixed_wing",
    "airliner_widebody": "fixed_wing",
    "regional_jet": "fixed_wing",
    "turboprop": "fixed_wing",
    "business_jet": "fixed_wing",
    "light_GA": "fixed_wing",
    "fighter": "fixed_wing",
    "military_transport": "fixed_wing",
    "fixed_wing_drone": "fixed_wing",
    "helicopter": "helicopter",
    "multirotor_drone": "multirotor",
}


@dataclass(frozen=True)
class Dihedral:
    """Wing dihedral (degrees) of a low, mid and high wing."""

    low: float = 5.0
    mid: float = 0.0
    high: float = 1.0

    def at(self, mount: str) -> float:
        return {"low": self.low, "mid": self.mid, "high": self.high}[mount]


@dataclass(frozen=True)
class Proportions:
    """What a fixed-wing category typically looks like."""

    diameter: float  # fuselage width / L
    height_ratio: float  # fuselage height / width
    aspect: float  # wing aspect ratio span^2 / area
    taper: float  # tip chord / root chord
    thickness: float  # wing thickness / chord
    wing_x: float  # root leading edge, fraction of L aft of the nose
    gear: float  # landing-gear drop below the fuselage, in D
    tail_span: float  # horizontal tail span / wing span
    profile: str  # fuselage profile, a key of PROFILES
    fuselage_exponent: float = 2.0  # cross-section superellipse exponent (> 2: boxier)
    fin_root: float = 0.20  # fin root chord / L
    nacelle: float = 0.055  # jet nacelle diameter / L
    prop_radius: float = 0.075  # propeller radius / L
    dihedral_deg: Dihedral = Dihedral()
    landing_gear: bool = True  # drawn down (low-altitude traffic near airfields)


CATEGORY = {
    "airliner_narrowbody": Proportions(0.105, 1.05, 9.5, 0.30, 0.12, 0.36, 0.45, 0.36,
                                       "airliner", nacelle=0.062),
    "airliner_widebody": Proportions(0.092, 1.08, 9.0, 0.28, 0.11, 0.36, 0.45, 0.34, "airliner",
                                     nacelle=0.050),
    "regional_jet": Proportions(0.095, 1.0, 8.5, 0.33, 0.12, 0.42, 0.40, 0.36, "airliner"),
    "turboprop": Proportions(0.095, 1.05, 11.0, 0.50, 0.15, 0.38, 0.45, 0.33, "airliner"),
    "business_jet": Proportions(0.085, 1.05, 8.0, 0.35, 0.11, 0.44, 0.35, 0.33, "business"),
    # a light aircraft's propeller is large for its size
    "light_GA": Proportions(0.14, 1.1, 7.5, 0.70, 0.15, 0.28, 0.45, 0.33, "light",
                            prop_radius=0.115),
    # boxy, blended fuselage; short fin chord; wings level whatever their height
    "fighter": Proportions(0.11, 0.85, 3.0, 0.25, 0.05, 0.40, 0.55, 0.45, "fighter",
                           fuselage_exponent=2.6, fin_root=0.16,
                           dihedral_deg=Dihedral(low=0.0, mid=0.0, high=0.0)),
    # high-winged transports droop their wings (anhedral)
    "military_transport": Proportions(0.125, 1.05, 8.5, 0.40, 0.14, 0.32, 0.20, 0.36,
                                      "transport", dihedral_deg=Dihedral(high=-2.0)),
    # small drones land on their belly or in a net
    "fixed_wing_drone": Proportions(0.10, 1.0, 12.0, 0.50, 0.12, 0.38, 0.30, 0.30, "light",
                                    landing_gear=False),
}


@dataclass(frozen=True)
class Profile:
    """A fuselage profile: (fraction of L from the nose, radius factor, centre height in D)
    stations, and the height (in D) of the tail cone where fin and tailplane sit."""

    stations: tuple
    tail_z: float = 0.2


PROFILES = {
    "airliner": Profile(((0, 0, -0.10), (0.02, 0.38, -0.08), (0.05, 0.68, -0.04),
                         (0.10, 0.93, 0), (0.16, 1, 0), (0.68, 1, 0), (0.80, 0.80, 0.10),
                         (0.90, 0.50, 0.24), (0.97, 0.22, 0.32), (1, 0, 0.34)), tail_z=0.34),
    "business": Profile(((0, 0, -0.05), (0.03, 0.45, -0.04), (0.09, 0.80, 0), (0.18, 1, 0),
                         (0.60, 1, 0), (0.75, 0.75, 0.08), (0.90, 0.42, 0.18), (1, 0, 0.25))),
    "transport": Profile(((0, 0, -0.05), (0.03, 0.55, -0.05), (0.08, 0.90, 0), (0.13, 1, 0),
                          (0.62, 1, 0.02), (0.75, 0.75, 0.18), (0.88, 0.42, 0.33),
                          (1, 0, 0.40))),
    "light": Profile(((0, 0, 0), (0.03, 0.50, 0), (0.10, 0.90, 0.05), (0.20, 1, 0.08),
                      (0.40, 0.90, 0.08), (0.65, 0.45, 0.12), (0.90, 0.25, 0.18),
                      (1, 0, 0.20))),
    "fighter": Profile(((0, 0, -0.05), (0.08, 0.32, -0.03), (0.20, 0.62, 0), (0.35, 0.95, 0),
                        (0.55, 1, 0), (0.85, 0.90, 0), (0.97, 0.65, 0), (1, 0, 0))),
}

# --- wing ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Mount:
    """Where the wing meets the fuselage."""

    z: float  # wing root height, in D
    prop_drop: float  # propeller nacelle centre below the wing, in nacelle diameters


# A high wing carries its propeller nacelles underneath; lower wings carry them on top.
MOUNTS = {"low": Mount(-0.30, -0.1), "mid": Mount(0.0, -0.1), "high": Mount(0.32, 0.15)}


@dataclass(frozen=True)
class Planform:
    """A wing layout; each value given here replaces the category's (None: keep it)."""

    aspect: float | None = None
    taper: float | None = None
    thickness: float | None = None
    wing_x: float | None = None
    dihedral_deg: float | None = None
    diameter: float | None = None  # fuselage (centre body) width / L
    profile: str | None = None
    root_chord: float | None = None  # / L; None: from the span and the aspect ratio
    sweep_reach: float | None = None  # tip leading edge at most this fraction of L aft
    foreplane: bool = False  # a canard
    tailplane: bool = True  # a tailplane behind the wing, where the tail has one


PLANFORMS = {
    "conventional": Planform(),
    # a delta behind a canard pitches with the canard: no tailplane; wing set well aft
    "canard_delta": Planform(aspect=2.4, taper=0.12, wing_x=0.35, dihedral_deg=-1.0,
                             foreplane=True, tailplane=False),
    # the wing, not the pod, sets the length: its tip trailing edge ends at the tail
    "flying_wing": Planform(taper=0.45, thickness=0.10, wing_x=0.05, diameter=0.22,
                            profile="light", root_chord=0.8, sweep_reach=0.55),
}


@dataclass(frozen=True)
class WingPosition:
    mount: str  # a key of MOUNTS
    planform: str = "conventional"  # a key of PLANFORMS
    wide_track: bool = False  # main gear spread out along the wing, not under the fuselage


# types.csv wing_position -> layout. A wing described as low (or low-mid) keeps its main gear
# in the wing, so the track is wide.
WING_POSITIONS = {
    "low": WingPosition("low", wide_track=True),
    "low-mid": WingPosition("mid", wide_track=True),
    "low-mid (canard delta)": WingPosition("mid", "canard_delta", wide_track=True),
    "mid": WingPosition("mid"),
    "mid (blended)": WingPosition("mid"),
    "mid (canard delta)": WingPosition("mid", "canard_delta"),
    "shoulder": WingPosition("high"),
    "high": WingPosition("high"),
    "high (shoulder)": WingPosition("high"),
    "high (strut-braced)": WingPosition("high"),
    "flying wing": WingPosition("mid", "flying_wing"),
    "flying wing (tailsitter VTOL)": WingPosition("mid", "flying_wing"),
    "blended wing (VTOL)": WingPosition("mid", "flying_wing"),
}

# --- tail ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Tail:
    style: str  # a key of builders.TAIL_PARTS (fixed wing) or an anti-torque (helicopter)
    fins: int = 1  # fins of a "fins" tail: 1 on the centreline or 2 apart
    cant_deg: float = 0.0  # twin fins lean outward
    tailplane: str = "root"  # on the fin: "root", "low_on_fin" (cruciform) or "top" (T-tail)
    tailplane_dihedral_deg: float = 0.0


# types.csv tail_type -> layout
TAIL_TYPES = {
    "conventional": Tail("fins"),
    "conventional (stabilator)": Tail("fins"),
    "conventional (stabiliser on tail cone, dihedral)": Tail("fins"),  # drawn flat
    "conventional (anhedral stabilator)": Tail("fins", tailplane_dihedral_deg=-10.0),
    "single fin": Tail("fins"),
    "T-tail": Tail("fins", tailplane="top"),
    "cruciform (stabiliser low on fin)": Tail("fins", tailplane="low_on_fin"),
    "twin fins": Tail("fins", fins=2),
    "twin canted fins": Tail("fins", fins=2, cant_deg=20.0),
    "twin fins (H-tail)": Tail("h_tail"),
    "V-tail": Tail("v_tail"),
    "inverted V-tail + ventral fin": Tail("inverted_v_tail"),
    "winglets": Tail("winglets"),
    "wingtip fins": Tail("winglets"),
    "vertical fins (also landing legs)": Tail("wing_fins"),
    "none (flying wing)": Tail("none"),
    # helicopters: what counters the rotor's torque
    "fenestron + horizontal stabiliser": Tail("fenestron"),
    "tail rotor + horizontal stabiliser": Tail("tail_rotor"),
    "tail rotor + small stabilisers": Tail("tail_rotor"),
    "canted tail rotor + stabilator": Tail("tail_rotor"),
    "none (tandem rotors)": Tail("none"),
}

# V-tail surfaces: length per fin height and lean from the vertical; they set the tail height
V_TAIL_LENGTH = 1.4
V_TAIL_CANT_DEG = 50
V_TAIL_RISE = V_TAIL_LENGTH * math.cos(V_TAIL_CANT_DEG * DEG)

# --- engines ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Engines:
    groups: frozenset  # keys of builders.ENGINE_PARTS
    on_wing: int | None = None  # engines on the wing when not all are; None: all


def _engines(*groups: str, on_wing: int | None = None) -> Engines:
    return Engines(frozenset(groups), on_wing)


# types.csv engine_placement -> engine groups (fixed wing only; rotorcraft draw their own)
ENGINE_PLACEMENTS = {
    "underwing pylons": _engines("wing"),
    "underwing nacelles": _engines("wing"),
    "underwing nacelles (also house main gear)": _engines("wing"),
    "wing nacelles": _engines("wing"),
    "wing-mounted tractors": _engines("wing"),
    "over-the-wing pylons": _engines("over_wing"),
    "2 underwing pylons + 1 in fin base": _engines("wing", "tail_centre", on_wing=2),
    "2 tilting wing motors + 1 rear": _engines("wing", "pusher_propeller", on_wing=2),
    "rear fuselage pods": _engines("rear_pods"),
    "2 rear fuselage pods + 1 centre (tail)": _engines("rear_pods", "tail_centre"),
    "2 rear fuselage pods + 1 centre (S-duct)": _engines("rear_pods", "tail_centre"),
    "2 rear fuselage pods + 1 centre (S-duct in tail)": _engines("rear_pods", "tail_centre"),
    "underslung nacelles": _engines("underslung"),
    "dorsal, rear fuselage": _engines("dorsal"),
    "internal, side intakes": _engines(),  # inside the fuselage: nothing to add
    "internal, ventral intake": _engines(),
    "nose": _engines("nose_propeller"),
    "nose tractor": _engines("nose_propeller"),
    "pusher": _engines("pusher_propeller"),
    "pusher, tail": _engines("pusher_propeller"),
    "pusher, rear of body": _engines("pusher_propeller"),
}

# types.csv propulsion -> whether the engines turn propellers (nacelle size, propeller discs)
PROPELLER_DRIVEN = {
    "turbofan": False,
    "turbojet": False,
    "turboshaft": False,
    "turboprop": True,
    "piston": True,
    "piston/propeller": True,
    "electric": True,
}

# --- per-type overrides ----------------------------------------------------------------------

# Layout fields (``builders.FixedWingLayout``, ``HelicopterLayout``, ``MultirotorLayout``) set
# for one type, where its listed facts alone would draw it wrongly.
TYPE_OVERRIDES = {
    # very slender high-altitude wings, far beyond the drone category's
    "RQ-4B Global Hawk": {"aspect": 25.0},
    # slender wing; the tall tricycle gear (the inverted V-tail points down) spans the height
    "MQ-9A Reaper": {"aspect": 18.0, "landing_gear": True, "gear_sets_height": True},
    # a straight-winged attack aircraft among swept fighters
    "A-10C Thunderbolt II": {"aspect": 6.5, "taper": 0.6},
    # its outer wing panels have strong dihedral, unlike the level wings of other fighters
    "F-4E Phantom II": {"dihedral_deg": 5.0},
    # skids, not wheels (dims_note)
    "206B-3 JetRanger III": {"skids": True},
    "R44 Raven II": {"skids": True},
    # listed dimensions include the propellers (dims_note)
    "Matrice 600 Pro": {"dims_include_rotors": True},
}
