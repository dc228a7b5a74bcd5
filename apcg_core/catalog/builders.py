"""Parametric aircraft, helicopter and drone meshes from a type's facts (plain numpy).

Each builder lays out the parts from the type's category (proportions typical of the
category) and its configuration (wing position, sweep, engine count and placement, tail type,
rotors), then the assembly is fitted to the listed length / span / height by a per-axis scale
(recorded, so tests can check the design was already close) and moved so that its volume
centroid is the origin. Body frame: x nose, y left wing, z up; metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..lidar import DEG
from .mesh import Mesh
from .shapes import body, box, cylinder, lifting_surface


@dataclass(frozen=True)
class Proportions:
    diameter: float  # fuselage width / length
    height_ratio: float  # fuselage height / width
    aspect: float  # wing aspect ratio span^2 / area
    taper: float  # tip chord / root chord
    thickness: float  # wing thickness / chord
    wing_x: float  # root leading edge, fraction of length aft of the nose
    gear: float  # landing-gear drop below the fuselage, in fuselage diameters
    tail_span: float  # horizontal tail span / wing span
    profile: str  # fuselage profile family


CATEGORY = {
    "airliner_narrowbody": Proportions(0.105, 1.05, 9.5, 0.30, 0.12, 0.36, 0.45, 0.36, "airliner"),
    "airliner_widebody": Proportions(0.092, 1.08, 9.0, 0.28, 0.11, 0.36, 0.45, 0.34, "airliner"),
    "regional_jet": Proportions(0.095, 1.0, 8.5, 0.33, 0.12, 0.42, 0.40, 0.36, "airliner"),
    "turboprop": Proportions(0.095, 1.05, 11.0, 0.50, 0.15, 0.38, 0.45, 0.33, "airliner"),
    "business_jet": Proportions(0.085, 1.05, 8.0, 0.35, 0.11, 0.44, 0.35, 0.33, "business"),
    "light_GA": Proportions(0.14, 1.1, 7.5, 0.70, 0.15, 0.28, 0.45, 0.33, "light"),
    "fighter": Proportions(0.11, 0.85, 3.0, 0.25, 0.05, 0.40, 0.55, 0.45, "fighter"),
    "military_transport": Proportions(0.125, 1.05, 8.5, 0.40, 0.14, 0.32, 0.20, 0.36, "transport"),
    "fixed_wing_drone": Proportions(0.10, 1.0, 12.0, 0.50, 0.12, 0.38, 0.30, 0.30, "light"),
}

# Fuselage profiles: (fraction of length from the nose, radius factor, centre height in D)
PROFILES = {
    "airliner": [(0, 0, -0.10), (0.02, 0.38, -0.08), (0.05, 0.68, -0.04), (0.10, 0.93, 0),
                 (0.16, 1, 0), (0.68, 1, 0), (0.80, 0.80, 0.10), (0.90, 0.50, 0.24),
                 (0.97, 0.22, 0.32), (1, 0, 0.34)],
    "business": [(0, 0, -0.05), (0.03, 0.45, -0.04), (0.09, 0.80, 0), (0.18, 1, 0),
                 (0.60, 1, 0), (0.75, 0.75, 0.08), (0.90, 0.42, 0.18), (1, 0, 0.25)],
    "transport": [(0, 0, -0.05), (0.03, 0.55, -0.05), (0.08, 0.90, 0), (0.13, 1, 0),
                  (0.62, 1, 0.02), (0.75, 0.75, 0.18), (0.88, 0.42, 0.33), (1, 0, 0.40)],
    "light": [(0, 0, 0), (0.03, 0.50, 0), (0.10, 0.90, 0.05), (0.20, 1, 0.08),
              (0.40, 0.90, 0.08), (0.65, 0.45, 0.12), (0.90, 0.25, 0.18), (1, 0, 0.20)],
    "fighter": [(0, 0, -0.05), (0.08, 0.32, -0.03), (0.20, 0.62, 0), (0.35, 0.95, 0),
                (0.55, 1, 0), (0.85, 0.90, 0), (0.97, 0.65, 0), (1, 0, 0)],
}


def fuselage(length: float, width: float, height_ratio: float, profile: str,
             n: int = 24, exponent: float = 2.0) -> Mesh:
    """Fuselage from nose (x = length / 2) to tail (x = -length / 2)."""
    rows = []
    for f, rf, zc in PROFILES[profile]:
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


def build_fixed_wing(t) -> Built:
    """Airliners, regional jets, turboprops, business jets, light aircraft, fighters,
    military transports and fixed-wing drones."""
    p = CATEGORY[t.category]
    L, S, Hh = t.length_m, t.span_m, t.height_m
    name = t.name.lower()
    place = t.engine_placement.lower()
    wingpos = t.wing_position.lower()
    tail = t.tail_type.lower()
    flying_wing = "flying wing" in wingpos or "blended wing" in wingpos
    canard = "canard" in wingpos
    D = p.diameter * L
    if flying_wing:
        D = 0.22 * L
    parts: list[Mesh] = []
    rotors: list[Mesh] = []
    profile = "light" if flying_wing else p.profile
    parts.append(fuselage(L, D, p.height_ratio, profile,
                          exponent=2.6 if t.category == "fighter" else 2.0))

    # --- wing ------------------------------------------------------------------------------
    sweep = (t.sweep_deg or 0.0) * DEG
    if t.sweep_ref == "c/4" and sweep > 0:
        sweep = math.atan(math.tan(sweep) + 0.04)  # leading edge sweeps a little more than c/4
    aspect, taper = p.aspect, p.taper
    if canard or ("delta" in wingpos):
        aspect, taper = 2.4, 0.12
    if flying_wing:
        aspect, taper = 5.0, 0.45
    if t.category == "fighter" and not sweep:  # straight-winged attack aircraft
        aspect, taper = 6.5, 0.6
    if "global hawk" in name:
        aspect = 25.0
    if "reaper" in name:
        aspect = 18.0
    mean_chord = S / aspect
    root = 2 * mean_chord / (1 + taper)
    if flying_wing:  # the wing, not the pod, sets the length: its tip trailing edge ends at the tail
        root, taper = 0.8 * L, 0.45
        sweep = min(sweep, math.atan(0.55 * L / (S / 2)))
    if "high" in wingpos or "shoulder" in wingpos:
        z_w, dih = 0.32 * D, -2.0 * DEG if t.category == "military_transport" else 1.0 * DEG
    elif "low" in wingpos and "mid" not in wingpos:
        z_w, dih = -0.30 * D, 5.0 * DEG
    else:
        z_w, dih = 0.0, 0.0
    if t.category == "fighter" and "anhedral" not in tail:
        dih = -1.0 * DEG if canard else 0.0
    x_le = L / 2 - p.wing_x * L
    if canard or flying_wing:
        x_le = L / 2 - 0.35 * L if canard else L / 2 - 0.05 * L
    wing = Wing(x_le, S / 2, root, root * taper, sweep, dih, z_w)
    parts.append(wing.mesh(p.thickness if not flying_wing else 0.10))
    if canard:
        cs = 0.38 * S / 2
        parts.append(Wing(L / 2 - 0.18 * L, cs, 0.12 * L, 0.04 * L, 45 * DEG, 0, 0.15 * D)
                     .mesh(0.05))

    # --- tail ------------------------------------------------------------------------------
    x_tail = -L / 2
    fin_root = 0.20 * L if t.category != "fighter" else 0.16 * L
    fin_sweep = min(max(sweep, 30 * DEG) + 5 * DEG, 50 * DEG)
    z_tail = 0.34 * D if profile in ("airliner",) else 0.2 * D
    bottom = -D / 2 * p.height_ratio
    has_gear = t.category != "fixed_wing_drone" or "reaper" in name
    drop = p.gear * D if has_gear else 0.0
    if "reaper" in name:
        drop = t.height_m - D
    # the fin sets the top: its height is what the listed height leaves above the gear
    vertical = 1.4 * math.cos(50 * DEG) if "v-tail" in tail and "inverted" not in tail else 1.0
    fin_h = float(np.clip((Hh - (z_tail - bottom + drop)) / vertical, 0.05 * L, 0.3 * L))
    if "twin" in tail:
        fin_h = float(np.clip(Hh - (0.2 * D - bottom + drop), 0.05 * L, 0.3 * L))
    fin_x = x_tail + max(fin_root * 1.02,
                         fin_h * math.tan(fin_sweep) + 0.45 * fin_root + 0.01 * L)
    ht_span = p.tail_span * S
    ht_root = 0.5 * root if not flying_wing else 0.0
    ht_sweep = sweep + 5 * DEG
    ht_x = x_tail + ht_root * 1.1
    ht_z = z_tail
    fins: list[tuple] = []
    if "none" in tail or (flying_wing and "fin" not in tail and "winglet" not in tail):
        pass
    elif "winglet" in tail or "wingtip fin" in tail:
        for s in (-1, 1):
            tip_x = wing.x_le(S / 2)
            parts.append(fin(tip_x + 0.05 * L, wing.tip_chord * 1.1, wing.tip_chord * 0.6,
                             0.18 * L, 35 * DEG, wing.z(S / 2), y=s * 0.995 * S / 2))
    elif "vertical fins" in tail:
        for s in (-1, 1):
            y = s * 0.3 * S / 2
            parts.append(fin(wing.x_le(y), wing.chord(y) * 0.9, wing.chord(y) * 0.5,
                             0.25 * L, 30 * DEG, wing.z(y) - 0.25 * L, y=y))
    elif "inverted v" in tail:
        for s in (-1, 1):
            parts.append(fin(fin_x, fin_root, 0.5 * fin_root, fin_h * 1.3, 20 * DEG, z_tail,
                             cant=s * 130 * DEG))
        parts.append(fin(fin_x, fin_root * 0.8, 0.4 * fin_root, fin_h * 0.6, 25 * DEG,
                         z_tail, cant=math.pi))
    elif "v-tail" in tail:
        for s in (-1, 1):
            parts.append(fin(fin_x, fin_root, 0.5 * fin_root, fin_h * 1.4, 20 * DEG, z_tail,
                             cant=s * 50 * DEG))
    elif "h-tail" in tail:
        parts.append(Wing(ht_x, ht_span / 2, ht_root, ht_root * 0.8, 0, 0, ht_z).mesh(0.10))
        for s in (-1, 1):
            parts.append(fin(ht_x + 0.02 * L, fin_root * 0.8, fin_root * 0.6, fin_h,
                             10 * DEG, ht_z - 0.4 * fin_h, y=s * ht_span / 2))
    else:
        twin = "twin" in tail
        canted = "canted" in tail
        if twin:
            for s in (-1, 1):
                fins.append((fin_x + 0.03 * L, s * 0.13 * S, 20 * DEG * s if canted else 0.0))
        else:
            fins.append((fin_x, 0.0, 0.0))
        for x, y, cant in fins:
            parts.append(fin(x, fin_root, 0.45 * fin_root, fin_h, fin_sweep,
                             z_tail if not twin else 0.2 * D, y=y, cant=cant))
        if "t-tail" in tail:
            ht_x = fin_x - fin_h * math.tan(fin_sweep) + 0.1 * fin_root
            ht_z = z_tail + fin_h * 0.98
            ht_root = 0.45 * fin_root
        elif "cruciform" in tail or "stabiliser low on fin" in tail:
            ht_x = fin_x - 0.4 * fin_h * math.tan(fin_sweep)
            ht_z = z_tail + 0.35 * fin_h
        if not canard and "single fin" not in tail or "f-16" in name:
            dih_t = -10 * DEG if "anhedral" in tail else 0.0
            parts.append(Wing(ht_x, ht_span / 2, ht_root, ht_root * 0.45, ht_sweep, dih_t,
                              ht_z).mesh(0.09))

    # --- engines ---------------------------------------------------------------------------
    n_eng = _count(t.n_engines, 1)
    prop = "turboprop" in t.propulsion or "piston" in t.propulsion or "electric" in t.propulsion
    Dn = {"airliner_widebody": 0.050, "airliner_narrowbody": 0.062}.get(t.category, 0.055) * L
    Ln = 2.2 * Dn
    if prop:
        Dn, Ln = 0.05 * L, 0.20 * L
    prop_r = (0.075 if t.category != "light_GA" else 0.115) * L
    if "underwing" in place or "wing nacelles" in place or "wing-mounted" in place \
            or "over-the-wing" in place or "tilting wing" in place:
        n_wing = 2 if "2 underwing" in place or "2 tilting" in place else n_eng
        n_side = max(1, n_wing // 2)
        fracs = [0.34] if n_side == 1 else [0.30, 0.62]
        for f in fracs:
            for s in (-1, 1):
                y = s * f * S / 2
                c = wing.chord(y)
                above = "over-the-wing" in place
                if prop:
                    cz = wing.z(y) - (0.15 * Dn if "high" in wingpos else -0.1 * Dn)
                    cx = wing.x_le(y) - 0.45 * c + Ln * 0.35
                    parts.append(nacelle((cx, y, cz), Ln, Dn))
                    rotors.append(disc((cx + Ln / 2 + 0.01 * L, y, cz), prop_r, "x", 0.004 * L))
                else:
                    cz = wing.z(y) + (0.75 if above else -0.65) * Dn
                    cx = wing.x_le(y) + (0.05 if above else 0.30) * Ln - (0.3 * c if above else 0)
                    parts.append(nacelle((cx, y, cz), Ln, Dn))
                    parts.append(box((cx - 0.15 * Ln, y, (cz + wing.z(y)) / 2),
                                     (0.7 * Ln, 0.12 * Dn, abs(cz - wing.z(y)) + 0.2 * Dn)))
    if "rear fuselage pods" in place or "rear pods" in place:
        x = x_tail + 0.30 * L
        for s in (-1, 1):
            y = s * (0.5 * D + 0.75 * Dn)
            parts.append(nacelle((x, y, 0.22 * D), Ln, Dn))
            parts.append(box((x, s * (0.25 * D + 0.4 * Dn), 0.22 * D),
                             (0.6 * Ln, 0.5 * D + 0.6 * Dn, 0.15 * Dn)))
    if "centre" in place or "fin base" in place:
        x = x_tail + 0.22 * L
        parts.append(nacelle((x, 0.0, 0.5 * D + 0.35 * Dn), Ln * 1.1, Dn * 0.9))
    if "underslung" in place:
        for s in (-1, 1):
            parts.append(nacelle((x_tail + 0.35 * L, s * 0.22 * D, -0.35 * D), 0.55 * L,
                                 0.35 * D))
    if "dorsal" in place:
        parts.append(nacelle((x_tail + 0.25 * L, 0.0, 0.5 * D), 0.25 * L, 0.35 * D))
    if place.startswith("nose") or "nose tractor" in place:
        rotors.append(disc((L / 2 + 0.01 * L, 0, 0), prop_r, "x", 0.004 * L))
    if "pusher" in place or ("+ 1 rear" in place):
        rotors.append(disc((x_tail - 0.01 * L, 0, 0.1 * D), prop_r * 1.2, "x", 0.004 * L))

    # --- landing gear (down: low-altitude traffic near airfields) -------------------------
    if has_gear:
        wheel = min(0.35 * drop + 0.02 * D, 0.4 * D)
        gx = x_le - 0.55 * root
        gy = 0.25 * D + (0.08 * S if "low" in wingpos else 0.0)
        parts += gear([(gx, gy), (gx, -gy)], bottom + 0.3 * D, drop + 0.3 * D, wheel)
        parts += gear([(L / 2 - 0.12 * L, 0.0)], bottom + 0.3 * D, drop + 0.3 * D, wheel * 0.8)
    return _assemble(parts, rotors, (L, S, Hh), fit_rotors=True)


def build_helicopter(t) -> Built:
    L, Drot, Hh = t.length_m, t.span_m, t.height_m
    R = (t.rotor_diameter_m or Drot) / 2
    tandem = _count(t.n_rotors, 1) == 2
    parts: list[Mesh] = []
    rotors: list[Mesh] = []
    if tandem:
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
    fenestron = "fenestron" in t.tail_type.lower()
    parts.append(fin(x_fin, 0.10 * Lb, 0.06 * Lb, 0.45 * W, 35 * DEG, 0.28 * W,
                     thickness=0.30 if fenestron else 0.12))
    parts.append(Wing(-Lb / 2 + 0.22 * Lb, 0.22 * W * 2.2, 0.06 * Lb, 0.045 * Lb, 0, 0, 0.25 * W)
                 .mesh(0.10))
    if not fenestron:
        rotors.append(disc((-Lb / 2 + 0.06 * Lb, 0.02 * W + 0.3 * boom_r, 0.55 * W),
                           0.09 * Lb, "y", 0.01 * Lb))
    top = W / 2 * 1.1 + 0.05 * W
    hub_x = Lb / 2 - 0.30 * Lb
    skids = "skid" in t.dims_note.lower()
    lowest = -W / 2 * 1.1 - (0.28 * W if skids else 0.2 * W)
    hub_z = max(top + 0.1 * W, lowest + Hh - 0.006 * R)  # the rotor head sets the height
    parts.append(box((hub_x - 0.05 * Lb, 0, top - 0.05 * W), (0.25 * Lb, 0.6 * W, 0.25 * W)))
    parts.append(cylinder([hub_x, 0, top - 0.05 * W], [hub_x, 0, hub_z], 0.07 * W, n=10))
    rotors.append(disc((hub_x, 0, hub_z), R, "z", 0.012 * R))
    bottom = -W / 2 * 1.1
    if skids:
        for s in (-1, 1):
            y = s * 0.45 * W
            z = bottom - 0.25 * W
            parts.append(cylinder([Lb / 2 - 0.15 * Lb, y, z], [Lb / 2 - 0.65 * Lb, y, z],
                                  0.03 * W, n=8))
            for x in (Lb / 2 - 0.25 * Lb, Lb / 2 - 0.5 * Lb):
                parts.append(cylinder([x, y * 0.6, bottom + 0.1 * W], [x, y, z], 0.025 * W, n=8))
    else:
        parts += gear([(Lb / 2 - 0.15 * Lb, 0.0), (Lb / 2 - 0.5 * Lb, 0.35 * W),
                       (Lb / 2 - 0.5 * Lb, -0.35 * W)], bottom + 0.1 * W, 0.3 * W, 0.15 * W)
    return _assemble(parts, rotors, (L, 2 * R, Hh), fit_rotors=True)


def build_multirotor(t) -> Built:
    L, S, Hh = t.length_m, t.span_m, t.height_m
    n = _count(t.n_rotors, 4)
    wb = t.diagonal_wheelbase_m or math.hypot(L, S)
    prop_r = (t.rotor_diameter_m or 0.3 * wb) / 2
    with_props = "with propellers" in t.dims_note.lower()
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


def build(t) -> Built:
    if t.category == "helicopter":
        return build_helicopter(t)
    if t.category == "multirotor_drone":
        return build_multirotor(t)
    return build_fixed_wing(t)
