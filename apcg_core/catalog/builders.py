"""Parametric aircraft, helicopter and drone meshes from a type's facts (plain numpy).

What to draw comes from data: the type's numbers in ``types.csv`` and the tables of
:mod:`.parts`, which give each category's proportions and say what each phrase of the type's
configuration (wing position, tail type, engine placement, propulsion) means for its parts;
a few types have an entry there that changes their layout. This module only draws: it never
looks at a type's name or searches its free text. The assembly is fitted to the listed length
/ span / height by a per-axis scale (recorded, so tests can check the design was already
close) and moved so that its volume centroid is the origin. Body frame: x nose, y left wing,
z up; metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields, replace

import numpy as np

from ..errors import InputError
from ..lidar import DEG
from .mesh import Mesh
from .parts import (
    BUILDER,
    CATEGORY,
    ENGINE_PLACEMENTS,
    MOUNTS,
    PLANFORMS,
    PROFILES,
    PROPELLER_DRIVEN,
    TAIL_TYPES,
    TYPE_OVERRIDES,
    V_TAIL_CANT_DEG,
    V_TAIL_LENGTH,
    V_TAIL_RISE,
    WING_POSITIONS,
    Engines,
    Tail,
)
from .shapes import body, box, cylinder, lifting_surface


def fuselage(length: float, width: float, height_ratio: float, profile: str,
             n: int = 24, exponent: float = 2.0) -> Mesh:
    """Fuselage from nose (x = length / 2) to tail (x = -length / 2)."""
    rows = []
    for f, rf, zc in PROFILES[profile].stations:
        x = length / 2 - f * length
        rows.append((x, max(rf, 1e-3) * width / 2, max(rf, 1e-3) * width / 2 * height_ratio,
                     0.0, zc * width))
    rows = rows[::-1]  # loft from tail to nose; winding is fixed by Mesh.outward
    return body(rows, n=n, exponent=exponent)


def nacelle(centre, length: float, diameter: float, n: int = 16) -> Mesh:
    """An engine nacelle / pod along x, blunt inlet, tapered exhaust."""
    cx, cy, cz = centre
    r = diameter / 2
    rows = [(cx + length / 2 + 1e-3, r * 0.6, r * 0.6, cy, cz),
            (cx + length / 2, r * 0.92, r * 0.92, cy, cz),
            (cx + length * 0.25, r, r, cy, cz),
            (cx - length * 0.30, r * 0.85, r * 0.85, cy, cz),
            (cx - length / 2, r * 0.55, r * 0.55, cy, cz),
            (cx - length / 2 - 1e-3, r * 0.3, r * 0.3, cy, cz)]
    return body(rows[::-1], n=n)


def disc(centre, radius: float, axis: str, thickness: float, n: int = 32) -> Mesh:
    """A thin disc: the swept area of a spinning propeller or rotor (what a photon-counting
    lidar integrating over many pulses sees of it)."""
    c = np.asarray(centre, float)
    a = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}[axis]
    a = np.asarray(a, float) * thickness / 2
    return cylinder(c - a, c + a, radius, n=n)


@dataclass
class Wing:
    x_le_root: float  # leading edge at the centreline
    semi_span: float
    root_chord: float
    tip_chord: float
    sweep: float  # leading-edge sweep (rad)
    dihedral: float  # rad
    z_root: float

    def x_le(self, y):
        return self.x_le_root - abs(y) * math.tan(self.sweep)

    def z(self, y):
        return self.z_root + abs(y) * math.tan(self.dihedral)

    def chord(self, y):
        return self.root_chord + (self.tip_chord - self.root_chord) * abs(y) / self.semi_span

    def mesh(self, thickness: float) -> Mesh:
        s = self.semi_span
        st = [(self.x_le(y), y, self.z(y), self.chord(y)) for y in (-s, -0.5 * s, 0.0, 0.5 * s, s)]
        return lifting_surface(st, thickness=thickness)


def fin(x_le_root: float, root_chord: float, tip_chord: float, height: float, sweep: float,
        z_root: float, y: float = 0.0, cant: float = 0.0, thickness: float = 0.10) -> Mesh:
    """A vertical (or canted) fin; cant > 0 leans its tip toward +y."""
    st = [(x_le_root, z_root - 0.05 * height, 0.0, root_chord),
          (x_le_root - height * math.tan(sweep), z_root + height, 0.0, tip_chord)]
    m = lifting_surface([(x, z, yy, c) for x, z, yy, c in st], thickness=thickness,
                        vertical=True)
    if cant:
        c, s = math.cos(cant), math.sin(cant)
        rot = np.array([[1, 0, 0], [0, c, s], [0, -s, c]])  # tilts +z toward +y
        m = Mesh(np.c_[m.vertices[:, 0], (m.vertices[:, 1:] - [0, z_root]) @ rot[1:, 1:].T
                       + [0, z_root]], m.faces)
    return m.transformed(offset=[0, y, 0])


def gear(points_xy, z_top: float, drop: float, wheel: float) -> list[Mesh]:
    """Struts from z_top down by ``drop`` with a wheel (a short cylinder along y) at each foot."""
    parts = []
    for x, y in points_xy:
        bottom = z_top - drop + wheel / 2
        parts.append(cylinder([x, y, z_top + 0.05 * drop], [x, y, bottom], wheel * 0.15, n=8))
        parts.append(cylinder([x, y - wheel * 0.2, bottom], [x, y + wheel * 0.2, bottom],
                              wheel / 2, n=12))
    return parts


@dataclass
class Built:
    mesh: Mesh
    fit_scale: np.ndarray  # per-axis scale applied to meet the listed extents
    rotor_faces: np.ndarray  # bool per face: propeller / rotor discs
    fitted_without_rotors: bool  # the listed dimensions exclude the propeller discs


def _assemble(parts: list[Mesh], rotors: list[Mesh], target, fit_rotors: bool) -> Built:
    """Concatenate parts, fit extents to ``target`` (x, y, z) and centre on the centroid."""
    allm = Mesh.concat(parts + rotors)
    without_rotors = bool(rotors) and not fit_rotors
    ref = Mesh.concat(parts) if without_rotors else allm
    scale = np.asarray(target, float) / ref.extents
    allm = allm.transformed(np.diag(scale))
    flags = np.r_[np.zeros(sum(len(p.faces) for p in parts), bool),
                  np.ones(sum(len(r.faces) for r in rotors), bool)]
    allm = allm.transformed(offset=-allm.centroid)
    return Built(allm, scale, flags, without_rotors)


def _count(text: str, default: int) -> int:
    try:
        return int(float(text))
    except (TypeError, ValueError):
        return default


# --- reading a type through the tables ---------------------------------------------------------


def _entry(table, key, what: str, context: str = ""):
    """``table[key]``, or an InputError naming the key and the accepted ones."""
    try:
        return table[key]
    except KeyError:
        accepted = ", ".join(repr(k) for k in table)
        raise InputError(f"{context}unknown {what} {key!r}; accepted: {accepted}") from None


def _vocab(t, column: str, table: dict):
    """What the phrase in the type's ``types.csv`` column means, from its table in .parts."""
    return _entry(table, getattr(t, column), column, context=f"{t.name}: ")


def _overridden(layout, t):
    """``layout`` with the fields that TYPE_OVERRIDES sets for this type."""
    changes = TYPE_OVERRIDES.get(t.name, {})
    accepted = [f.name for f in fields(layout)]
    unknown = sorted(set(changes) - set(accepted))
    if unknown:
        raise InputError(f"{t.name}: TYPE_OVERRIDES sets {', '.join(unknown)}, not fields of "
                         f"{type(layout).__name__}; accepted: {', '.join(accepted)}")
    return replace(layout, **changes)


def _given(value, default):
    return default if value is None else value


@dataclass(frozen=True)
class FixedWingLayout:
    """A fixed-wing type's parts: its category's proportions as its planform changes them,
    the meaning of its configuration phrases, then its TYPE_OVERRIDES entry. Lengths are
    fractions of the listed length (L) or of the fuselage diameter (D), as in .parts."""

    # fuselage
    diameter: float
    height_ratio: float
    profile: str
    fuselage_exponent: float
    # wing
    mount: str
    aspect: float
    taper: float
    thickness: float
    wing_x: float
    dihedral_deg: float
    root_chord: float | None
    sweep_reach: float | None
    foreplane: bool
    # tail
    tail: Tail
    tailplane: bool
    tail_span: float
    fin_root: float
    # engines
    engines: Engines
    propeller: bool
    nacelle: float
    prop_radius: float
    # landing gear
    landing_gear: bool
    gear: float
    gear_sets_height: bool  # the gear, not the fin, spans the listed height
    wide_track: bool


def fixed_wing_layout(t) -> FixedWingLayout:
    """The type's layout, read from the tables of .parts."""
    p = _entry(CATEGORY, t.category, "fixed-wing category", context=f"{t.name}: ")
    pos = _vocab(t, "wing_position", WING_POSITIONS)
    plan = PLANFORMS[pos.planform]
    layout = FixedWingLayout(
        diameter=_given(plan.diameter, p.diameter), height_ratio=p.height_ratio,
        profile=_given(plan.profile, p.profile), fuselage_exponent=p.fuselage_exponent,
        mount=pos.mount, aspect=_given(plan.aspect, p.aspect), taper=_given(plan.taper, p.taper),
        thickness=_given(plan.thickness, p.thickness), wing_x=_given(plan.wing_x, p.wing_x),
        dihedral_deg=_given(plan.dihedral_deg, p.dihedral_deg.at(pos.mount)),
        root_chord=plan.root_chord, sweep_reach=plan.sweep_reach, foreplane=plan.foreplane,
        tail=_vocab(t, "tail_type", TAIL_TYPES), tailplane=plan.tailplane,
        tail_span=p.tail_span, fin_root=p.fin_root,
        engines=_vocab(t, "engine_placement", ENGINE_PLACEMENTS),
        propeller=_vocab(t, "propulsion", PROPELLER_DRIVEN), nacelle=p.nacelle,
        prop_radius=p.prop_radius, landing_gear=p.landing_gear, gear=p.gear,
        gear_sets_height=False, wide_track=pos.wide_track)
    return _overridden(layout, t)


# --- fixed wing: airframe ----------------------------------------------------------------------


@dataclass(frozen=True)
class Airframe:
    """A fixed-wing type's main dimensions (m), shared by its part builders."""

    L: float
    S: float
    D: float  # fuselage diameter
    wing: Wing
    bottom: float  # underside of the fuselage
    drop: float  # landing gear below it
    x_tail: float  # tail end of the fuselage
    z_tail: float  # fin root height
    fin_root: float  # fin root chord
    fin_sweep: float
    fin_h: float
    fin_x: float  # fin root leading edge


def _sweep(t, lay: FixedWingLayout) -> float:
    sweep = (t.sweep_deg or 0.0) * DEG
    if t.sweep_ref == "c/4" and sweep > 0:
        sweep = math.atan(math.tan(sweep) + 0.04)  # leading edge sweeps a little more than c/4
    if lay.sweep_reach is not None:
        sweep = min(sweep, math.atan(lay.sweep_reach * t.length_m / (t.span_m / 2)))
    return sweep


def _main_wing(t, lay: FixedWingLayout, D: float) -> Wing:
    L, S = t.length_m, t.span_m
    if lay.root_chord is None:
        root = 2 * (S / lay.aspect) / (1 + lay.taper)  # mean chord S / aspect
    else:
        root = lay.root_chord * L
    return Wing(L / 2 - lay.wing_x * L, S / 2, root, root * lay.taper, _sweep(t, lay),
                lay.dihedral_deg * DEG, MOUNTS[lay.mount].z * D)


def _gear_drop(t, lay: FixedWingLayout, D: float) -> float:
    if not lay.landing_gear:
        return 0.0
    return t.height_m - D if lay.gear_sets_height else lay.gear * D


def _airframe(t, lay: FixedWingLayout) -> Airframe:
    L, S = t.length_m, t.span_m
    D = lay.diameter * L
    wing = _main_wing(t, lay, D)
    bottom = -D / 2 * lay.height_ratio
    drop = _gear_drop(t, lay, D)
    z_tail = PROFILES[lay.profile].tail_z * D
    fin_root = lay.fin_root * L
    fin_sweep = min(max(wing.sweep, 30 * DEG) + 5 * DEG, 50 * DEG)
    # the fin sets the top: its height is what the listed height leaves above the gear
    rise = _tail_part(lay).rise
    fin_h = float(np.clip((t.height_m - (z_tail - bottom + drop)) / rise, 0.05 * L, 0.3 * L))
    fin_x = -L / 2 + max(fin_root * 1.02,
                         fin_h * math.tan(fin_sweep) + 0.45 * fin_root + 0.01 * L)
    return Airframe(L, S, D, wing, bottom, drop, -L / 2, z_tail, fin_root, fin_sweep, fin_h,
                    fin_x)


def _foreplane(a: Airframe) -> Mesh:
    """A canard ahead of the wing, a little above it."""
    L = a.L
    return Wing(L / 2 - 0.18 * L, 0.38 * a.S / 2, 0.12 * L, 0.04 * L, 45 * DEG, 0,
                0.15 * a.D).mesh(0.05)


# --- fixed wing: tails -------------------------------------------------------------------------


def _no_tail(a: Airframe, lay: FixedWingLayout) -> list[Mesh]:
    return []


def _winglets(a: Airframe, lay: FixedWingLayout) -> list[Mesh]:
    """Upright fins on the wing tips."""
    w, L, S = a.wing, a.L, a.S
    tip_x = w.x_le(S / 2)
    return [fin(tip_x + 0.05 * L, w.tip_chord * 1.1, w.tip_chord * 0.6, 0.18 * L, 35 * DEG,
                w.z(S / 2), y=s * 0.995 * S / 2) for s in (-1, 1)]


def _wing_fins(a: Airframe, lay: FixedWingLayout) -> list[Mesh]:
    """Fins through the wing at 30 % of the semi-span, reaching below it (landing legs)."""
    w, L = a.wing, a.L
    parts = []
    for s in (-1, 1):
        y = s * 0.3 * a.S / 2
        parts.append(fin(w.x_le(y), w.chord(y) * 0.9, w.chord(y) * 0.5, 0.25 * L, 30 * DEG,
                         w.z(y) - 0.25 * L, y=y))
    return parts


def _inverted_v_tail(a: Airframe, lay: FixedWingLayout) -> list[Mesh]:
    """Two surfaces leaning down and out, and a ventral fin."""
    r = a.fin_root
    parts = [fin(a.fin_x, r, 0.5 * r, a.fin_h * 1.3, 20 * DEG, a.z_tail, cant=s * 130 * DEG)
             for s in (-1, 1)]
    parts.append(fin(a.fin_x, r * 0.8, 0.4 * r, a.fin_h * 0.6, 25 * DEG, a.z_tail, cant=math.pi))
    return parts


def _v_tail(a: Airframe, lay: FixedWingLayout) -> list[Mesh]:
    r = a.fin_root
    return [fin(a.fin_x, r, 0.5 * r, a.fin_h * V_TAIL_LENGTH, 20 * DEG, a.z_tail,
                cant=s * V_TAIL_CANT_DEG * DEG) for s in (-1, 1)]


def _h_tail(a: Airframe, lay: FixedWingLayout) -> list[Mesh]:
    """A tailplane with a fin at each end."""
    span, root = lay.tail_span * a.S, 0.5 * a.wing.root_chord
    x, z = a.x_tail + root * 1.1, a.z_tail
    parts = [Wing(x, span / 2, root, root * 0.8, 0, 0, z).mesh(0.10)]
    for s in (-1, 1):
        parts.append(fin(x + 0.02 * a.L, a.fin_root * 0.8, a.fin_root * 0.6, a.fin_h, 10 * DEG,
                         z - 0.4 * a.fin_h, y=s * span / 2))
    return parts


# Where a fins tail's tailplane sits: (root chord, root leading edge x, height)
TAILPLANE_PLACES: dict[str, Callable[[Airframe], tuple[float, float, float]]] = {
    "root": lambda a: (0.5 * a.wing.root_chord, a.x_tail + 0.5 * a.wing.root_chord * 1.1,
                       a.z_tail),
    "low_on_fin": lambda a: (0.5 * a.wing.root_chord,
                             a.fin_x - 0.4 * a.fin_h * math.tan(a.fin_sweep),
                             a.z_tail + 0.35 * a.fin_h),
    # on the fin tip, with a chord to match the fin's
    "top": lambda a: (0.45 * a.fin_root,
                      a.fin_x - a.fin_h * math.tan(a.fin_sweep) + 0.1 * a.fin_root,
                      a.z_tail + a.fin_h * 0.98),
}


def _tailplane(a: Airframe, lay: FixedWingLayout) -> Mesh:
    place = _entry(TAILPLANE_PLACES, lay.tail.tailplane, "tailplane place")
    root, x, z = place(a)
    span = lay.tail_span * a.S
    return Wing(x, span / 2, root, root * 0.45, a.wing.sweep + 5 * DEG,
                lay.tail.tailplane_dihedral_deg * DEG, z).mesh(0.09)


def _fins_and_tailplane(a: Airframe, lay: FixedWingLayout) -> list[Mesh]:
    """One fin on the centreline, or two apart (leaning out when canted), and the tailplane
    unless the planform has none (a canard delta)."""
    tail = lay.tail
    if tail.fins == 1:
        places = [(a.fin_x, 0.0, 0.0)]
    else:
        places = [(a.fin_x + 0.03 * a.L, s * 0.13 * a.S, tail.cant_deg * DEG * s)
                  for s in (-1, 1)]
    parts = [fin(x, a.fin_root, 0.45 * a.fin_root, a.fin_h, a.fin_sweep, a.z_tail, y=y,
                 cant=cant) for x, y, cant in places]
    if lay.tailplane:
        parts.append(_tailplane(a, lay))
    return parts


@dataclass(frozen=True)
class TailPart:
    draw: Callable[[Airframe, FixedWingLayout], list[Mesh]]
    rise: float = 1.0  # height of the tail's top above its root, per fin height


# Tail.style -> its parts (fixed wing)
TAIL_PARTS = {
    "none": TailPart(_no_tail),
    "winglets": TailPart(_winglets),
    "wing_fins": TailPart(_wing_fins),
    "inverted_v_tail": TailPart(_inverted_v_tail),
    "v_tail": TailPart(_v_tail, rise=V_TAIL_RISE),
    "h_tail": TailPart(_h_tail),
    "fins": TailPart(_fins_and_tailplane),
}


def _tail_part(lay: FixedWingLayout) -> TailPart:
    return _entry(TAIL_PARTS, lay.tail.style, "fixed-wing tail style")


# --- fixed wing: engines -----------------------------------------------------------------------


Drawn = tuple[list[Mesh], list[Mesh]]  # parts, propeller / rotor discs


@dataclass(frozen=True)
class Powerplant:
    """A fixed-wing type's engines: how many and how big (m)."""

    count: int
    diameter: float  # nacelle (m)
    length: float
    prop_radius: float
    propeller: bool


def _powerplant(t, lay: FixedWingLayout) -> Powerplant:
    L = t.length_m
    Dn = lay.nacelle * L
    Ln = 2.2 * Dn
    if lay.propeller:
        Dn, Ln = 0.05 * L, 0.20 * L
    return Powerplant(_count(t.n_engines, 1), Dn, Ln, lay.prop_radius * L, lay.propeller)


def _propeller_nacelle(a: Airframe, lay: FixedWingLayout, pp: Powerplant,
                       y: float) -> tuple[Mesh, Mesh]:
    """A nacelle on the wing (below a high wing, above a lower one) and its propeller disc."""
    w, Ln, Dn = a.wing, pp.length, pp.diameter
    cz = w.z(y) - MOUNTS[lay.mount].prop_drop * Dn
    cx = w.x_le(y) - 0.45 * w.chord(y) + Ln * 0.35
    return (nacelle((cx, y, cz), Ln, Dn),
            disc((cx + Ln / 2 + 0.01 * a.L, y, cz), pp.prop_radius, "x", 0.004 * a.L))


def _jet_pod(a: Airframe, pp: Powerplant, y: float, above: bool) -> list[Mesh]:
    """A jet nacelle on a pylon, ahead of and below the wing, or above its rear."""
    w, Ln, Dn = a.wing, pp.length, pp.diameter
    lift, ahead, back = (0.75, 0.05, 0.3) if above else (-0.65, 0.30, 0.0)
    cz = w.z(y) + lift * Dn
    cx = w.x_le(y) + ahead * Ln - back * w.chord(y)
    pylon = box((cx - 0.15 * Ln, y, (cz + w.z(y)) / 2),
                (0.7 * Ln, 0.12 * Dn, abs(cz - w.z(y)) + 0.2 * Dn))
    return [nacelle((cx, y, cz), Ln, Dn), pylon]


def _wing_engines(a: Airframe, lay: FixedWingLayout, pp: Powerplant,
                  above: bool = False) -> Drawn:
    """One or two engines a side on the wing (all of them unless the placement says how
    many are there)."""
    n_side = max(1, (lay.engines.on_wing or pp.count) // 2)
    stations = [0.34] if n_side == 1 else [0.30, 0.62]  # fractions of the semi-span
    parts, rotors = [], []
    for f in stations:
        for s in (-1, 1):
            y = s * f * a.S / 2
            if pp.propeller:
                pod, prop = _propeller_nacelle(a, lay, pp, y)
                parts.append(pod)
                rotors.append(prop)
            else:
                parts += _jet_pod(a, pp, y, above)
    return parts, rotors


def _rear_pods(a: Airframe, lay: FixedWingLayout, pp: Powerplant) -> Drawn:
    """A pod each side of the rear fuselage on a stub pylon."""
    D, Ln, Dn = a.D, pp.length, pp.diameter
    x = a.x_tail + 0.30 * a.L
    parts = []
    for s in (-1, 1):
        y = s * (0.5 * D + 0.75 * Dn)
        parts.append(nacelle((x, y, 0.22 * D), Ln, Dn))
        parts.append(box((x, s * (0.25 * D + 0.4 * Dn), 0.22 * D),
                         (0.6 * Ln, 0.5 * D + 0.6 * Dn, 0.15 * Dn)))
    return parts, []


def _tail_centre(a: Airframe, lay: FixedWingLayout, pp: Powerplant) -> Drawn:
    """A centre engine on top of the rear fuselage (S-duct or fin base)."""
    return [nacelle((a.x_tail + 0.22 * a.L, 0.0, 0.5 * a.D + 0.35 * pp.diameter),
                    pp.length * 1.1, pp.diameter * 0.9)], []


def _underslung(a: Airframe, lay: FixedWingLayout, pp: Powerplant) -> Drawn:
    """Two long engine nacelles under the rear fuselage."""
    L, D = a.L, a.D
    return [nacelle((a.x_tail + 0.35 * L, s * 0.22 * D, -0.35 * D), 0.55 * L, 0.35 * D)
            for s in (-1, 1)], []


def _dorsal(a: Airframe, lay: FixedWingLayout, pp: Powerplant) -> Drawn:
    return [nacelle((a.x_tail + 0.25 * a.L, 0.0, 0.5 * a.D), 0.25 * a.L, 0.35 * a.D)], []


def _nose_propeller(a: Airframe, lay: FixedWingLayout, pp: Powerplant) -> Drawn:
    L = a.L
    return [], [disc((L / 2 + 0.01 * L, 0, 0), pp.prop_radius, "x", 0.004 * L)]


def _pusher_propeller(a: Airframe, lay: FixedWingLayout, pp: Powerplant) -> Drawn:
    L = a.L
    return [], [disc((a.x_tail - 0.01 * L, 0, 0.1 * a.D), pp.prop_radius * 1.2, "x",
                     0.004 * L)]


# Engine group -> its (parts, propeller discs); drawn in this order
ENGINE_PARTS = {
    "wing": _wing_engines,
    "over_wing": lambda a, lay, pp: _wing_engines(a, lay, pp, above=True),
    "rear_pods": _rear_pods,
    "tail_centre": _tail_centre,
    "underslung": _underslung,
    "dorsal": _dorsal,
    "nose_propeller": _nose_propeller,
    "pusher_propeller": _pusher_propeller,
}


def _engines(t, a: Airframe, lay: FixedWingLayout) -> Drawn:
    for group in sorted(lay.engines.groups):
        _entry(ENGINE_PARTS, group, "engine group", context=f"{t.name}: ")
    pp = _powerplant(t, lay)
    parts: list[Mesh] = []
    rotors: list[Mesh] = []
    for group, draw in ENGINE_PARTS.items():
        if group in lay.engines.groups:
            more_parts, more_rotors = draw(a, lay, pp)
            parts += more_parts
            rotors += more_rotors
    return parts, rotors


# --- fixed wing: assembly ----------------------------------------------------------------------


def _landing_gear(a: Airframe, lay: FixedWingLayout) -> list[Mesh]:
    """Main gear behind the wing root (spread along a low wing) and a nose gear; down, as
    seen by low-altitude traffic near airfields."""
    L, D = a.L, a.D
    wheel = min(0.35 * a.drop + 0.02 * D, 0.4 * D)
    gx = a.wing.x_le_root - 0.55 * a.wing.root_chord
    gy = 0.25 * D + (0.08 * a.S if lay.wide_track else 0.0)
    top, drop = a.bottom + 0.3 * D, a.drop + 0.3 * D
    return (gear([(gx, gy), (gx, -gy)], top, drop, wheel)
            + gear([(L / 2 - 0.12 * L, 0.0)], top, drop, wheel * 0.8))


def build_fixed_wing(t) -> Built:
    """Airliners, regional jets, turboprops, business jets, light aircraft, fighters,
    military transports and fixed-wing drones."""
    lay = fixed_wing_layout(t)
    a = _airframe(t, lay)
    parts = [fuselage(a.L, a.D, lay.height_ratio, lay.profile,
                      exponent=lay.fuselage_exponent),
             a.wing.mesh(lay.thickness)]
    if lay.foreplane:
        parts.append(_foreplane(a))
    parts += _tail_part(lay).draw(a, lay)
    engine_parts, rotors = _engines(t, a, lay)
    parts += engine_parts
    if lay.landing_gear:
        parts += _landing_gear(a, lay)
    return _assemble(parts, rotors, (t.length_m, t.span_m, t.height_m), fit_rotors=True)


# --- helicopters -------------------------------------------------------------------------------


@dataclass(frozen=True)
class HelicopterLayout:
    fin_thickness: float  # / chord
    tail_rotor: bool
    skids: bool = False  # else wheels


# Tail.style -> (fin thickness, tail rotor): a fenestron is a thick ducted fin
ANTI_TORQUE = {"tail_rotor": (0.12, True), "fenestron": (0.30, False), "none": (0.12, False)}


def helicopter_layout(t) -> HelicopterLayout:
    style = _vocab(t, "tail_type", TAIL_TYPES).style
    thickness, tail_rotor = _entry(ANTI_TORQUE, style, "helicopter tail style",
                                   context=f"{t.name}: ")
    return _overridden(HelicopterLayout(thickness, tail_rotor), t)


def _tandem_helicopter(t) -> Built:
    L, Drot, Hh = t.length_m, t.span_m, t.height_m
    R = (t.rotor_diameter_m or Drot) / 2
    parts: list[Mesh] = []
    rotors: list[Mesh] = []
    Lb = L - 2 * R + 2 * 0.12 * (L - 2 * R) / 0.76  # hubs sit 12 % in from each end
    W = 0.25 * Lb
    rows = [(Lb / 2, 0, 0, 0, 0), (Lb / 2 - 0.03 * Lb, 0.7 * W / 2, 0.7 * W / 2, 0, -0.05 * W),
            (Lb / 2 - 0.10 * Lb, W / 2, W / 2 * 1.05, 0, 0),
            (-Lb / 2 + 0.05 * Lb, W / 2, W / 2 * 1.05, 0, 0.05 * W), (-Lb / 2, 0, 0, 0, 0.1 * W)]
    parts.append(body(rows[::-1], exponent=3.0))
    top = W / 2 * 1.05
    aft_z = max(top + 0.2 * W, -W / 2 * 1.05 - 0.35 * W + Hh - 0.006 * R)
    hubs = [(Lb / 2 - 0.12 * Lb, aft_z - 0.25 * (aft_z - top)), (-Lb / 2 + 0.12 * Lb, aft_z)]
    parts.append(box((-Lb / 2 + 0.12 * Lb, 0, (top + aft_z) / 2 - 0.1 * W),
                     (0.22 * Lb, 0.35 * W, aft_z - top)))
    for x, z in hubs:
        parts.append(cylinder([x, 0, top - 0.05 * W], [x, 0, z], 0.06 * W, n=10))
        rotors.append(disc((x, 0, z), R, "z", 0.012 * R))
    bottom = -W / 2 * 1.05
    wheel = 0.25 * W
    parts += gear([(Lb / 3, W / 3), (Lb / 3, -W / 3), (-Lb / 3, W / 3), (-Lb / 3, -W / 3)],
                  bottom + 0.1 * W, 0.45 * W, wheel)
    return _assemble(parts, rotors, (L, 2 * R, Hh), fit_rotors=True)


def _skids(Lb: float, W: float, bottom: float) -> list[Mesh]:
    parts = []
    for s in (-1, 1):
        y = s * 0.45 * W
        z = bottom - 0.25 * W
        parts.append(cylinder([Lb / 2 - 0.15 * Lb, y, z], [Lb / 2 - 0.65 * Lb, y, z],
                              0.03 * W, n=8))
        for x in (Lb / 2 - 0.25 * Lb, Lb / 2 - 0.5 * Lb):
            parts.append(cylinder([x, y * 0.6, bottom + 0.1 * W], [x, y, z], 0.025 * W, n=8))
    return parts


def _single_rotor_helicopter(t, lay: HelicopterLayout) -> Built:
    L, Drot, Hh = t.length_m, t.span_m, t.height_m
    R = (t.rotor_diameter_m or Drot) / 2
    parts: list[Mesh] = []
    rotors: list[Mesh] = []
    Lb = (L - R) / 0.70  # the rotor hub sits 30 % of the body length aft of the nose
    W = 0.17 * Lb
    cabin = [(Lb / 2, 0, 0, 0, -0.1 * W), (Lb / 2 - 0.04 * Lb, 0.55 * W / 2, 0.6 * W / 2, 0, -0.1 * W),
             (Lb / 2 - 0.12 * Lb, 0.92 * W / 2, W / 2 * 1.1, 0, 0),
             (Lb / 2 - 0.45 * Lb, W / 2, W / 2 * 1.1, 0, 0.05 * W),
             (Lb / 2 - 0.58 * Lb, 0.5 * W / 2, 0.6 * W / 2, 0, 0.20 * W), (Lb / 2 - 0.62 * Lb, 0, 0, 0, 0.25 * W)]
    parts.append(body(cabin[::-1], exponent=2.4))
    boom_r = 0.09 * W
    parts.append(cylinder([Lb / 2 - 0.50 * Lb, 0, 0.22 * W], [-Lb / 2 + 0.05 * Lb, 0, 0.28 * W],
                          boom_r * 1.6, n=12))
    x_fin = -Lb / 2 + 0.10 * Lb
    parts.append(fin(x_fin, 0.10 * Lb, 0.06 * Lb, 0.45 * W, 35 * DEG, 0.28 * W,
                     thickness=lay.fin_thickness))
    parts.append(Wing(-Lb / 2 + 0.22 * Lb, 0.22 * W * 2.2, 0.06 * Lb, 0.045 * Lb, 0, 0, 0.25 * W)
                 .mesh(0.10))
    if lay.tail_rotor:
        rotors.append(disc((-Lb / 2 + 0.06 * Lb, 0.02 * W + 0.3 * boom_r, 0.55 * W),
                           0.09 * Lb, "y", 0.01 * Lb))
    top = W / 2 * 1.1 + 0.05 * W
    hub_x = Lb / 2 - 0.30 * Lb
    lowest = -W / 2 * 1.1 - (0.28 * W if lay.skids else 0.2 * W)
    hub_z = max(top + 0.1 * W, lowest + Hh - 0.006 * R)  # the rotor head sets the height
    parts.append(box((hub_x - 0.05 * Lb, 0, top - 0.05 * W), (0.25 * Lb, 0.6 * W, 0.25 * W)))
    parts.append(cylinder([hub_x, 0, top - 0.05 * W], [hub_x, 0, hub_z], 0.07 * W, n=10))
    rotors.append(disc((hub_x, 0, hub_z), R, "z", 0.012 * R))
    bottom = -W / 2 * 1.1
    if lay.skids:
        parts += _skids(Lb, W, bottom)
    else:
        parts += gear([(Lb / 2 - 0.15 * Lb, 0.0), (Lb / 2 - 0.5 * Lb, 0.35 * W),
                       (Lb / 2 - 0.5 * Lb, -0.35 * W)], bottom + 0.1 * W, 0.3 * W, 0.15 * W)
    return _assemble(parts, rotors, (L, 2 * R, Hh), fit_rotors=True)


def build_helicopter(t) -> Built:
    if _count(t.n_rotors, 1) == 2:
        return _tandem_helicopter(t)
    return _single_rotor_helicopter(t, helicopter_layout(t))


# --- multirotor drones -------------------------------------------------------------------------


@dataclass(frozen=True)
class MultirotorLayout:
    dims_include_rotors: bool = False  # the listed length / span include the propellers


def build_multirotor(t) -> Built:
    L, S, Hh = t.length_m, t.span_m, t.height_m
    n = _count(t.n_rotors, 4)
    wb = t.diagonal_wheelbase_m or math.hypot(L, S)
    prop_r = (t.rotor_diameter_m or 0.3 * wb) / 2
    with_props = _overridden(MultirotorLayout(), t).dims_include_rotors
    motor_r = 0.045 * wb
    edge = prop_r if with_props else motor_r
    # motors on an ellipse whose extents (plus a motor or a propeller) are the listed ones
    ax, ay = max(L / 2 - edge, 0.2 * L), max(S / 2 - edge, 0.2 * S)
    parts: list[Mesh] = []
    rotors: list[Mesh] = []
    bw = min(0.30 * wb, 0.6 * min(L, S))
    bh = 0.30 * Hh
    parts.append(body([(bw * 0.75, 0, 0, 0, 0), (bw * 0.6, bw * 0.3, bh * 0.4, 0, 0),
                       (0.0, bw * 0.45, bh / 2, 0, 0), (-bw * 0.6, bw * 0.3, bh * 0.4, 0, 0),
                       (-bw * 0.75, 0, 0, 0, 0)][::-1], exponent=3.0))
    offset = math.pi / n  # "X" layout: no arm straight ahead
    for k in range(n):
        a = offset + 2 * math.pi * k / n
        tip = np.array([ax * math.cos(a), ay * math.sin(a), 0.1 * bh])
        tip[:2] /= max(abs(math.cos(a)), abs(math.sin(a))) if n == 4 else 1.0
        parts.append(cylinder([0, 0, 0.1 * bh], tip, 0.03 * wb, n=8))
        parts.append(cylinder(tip - [0, 0, 0.12 * Hh], tip + [0, 0, 0.12 * Hh], motor_r, n=12))
        rotors.append(disc(tip + [0, 0, 0.14 * Hh], prop_r, "z", 0.01 * prop_r))
    legz = 0.1 * bh + 0.12 * Hh - Hh + 0.012 * wb  # the legs set the height
    for s in (-1, 1):
        y = s * 0.3 * min(S, wb)
        parts.append(cylinder([0.25 * bw * 2, y, legz], [-0.25 * bw * 2, y, legz], 0.012 * wb, n=8))
        parts.append(cylinder([0, s * 0.12 * bw, -bh / 4], [0, y, legz], 0.012 * wb, n=8))
    return _assemble(parts, rotors, (L, S, Hh), fit_rotors=with_props)


BUILDERS = {"fixed_wing": build_fixed_wing, "helicopter": build_helicopter,
            "multirotor": build_multirotor}


def build(t) -> Built:
    """The type's mesh, by the builder its category names in .parts."""
    return BUILDERS[_entry(BUILDER, t.category, "category", context=f"{t.name}: ")](t)
