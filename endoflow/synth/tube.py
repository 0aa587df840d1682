"""A colon-like tube made of conical slabs, and its exact intersection with camera rays.

Watertight by construction, with texture coordinates continuous across joints; units cm. Rays are
``R K^-1 [u, v, 1]``, so a hit's ray parameter is its z-depth. See docs/synthetic_data.md, "How a colon is made".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

# Hits within this distance (cm) outside a slab's planes still count: a point on a joint plane must be
# found by one of the two slabs despite rounding.
PLANE_TOLERANCE_CM = 1e-4
NEAREST_HIT_CM = 1e-4
SLAB_MARGIN = 1.3  # the planes of a slab may meet no closer to the axis than this many radii
PLANES_PER_CHUNK = 12
FIRST_CHUNK = 8
RING_TOLERANCE = 1e-4  # relative (of r^2): crossings this close to a ring count as outside it
FOLD_PIECES = 8  # cones per haustral fold


@dataclass
class TubeShape:
    """Parameters of one tube family (a SimCol scene, an EndoSLAM organ). Lengths in cm, angles in rad."""

    radius: tuple[float, float]  # range of the slowly varying lumen radius
    radius_wavelength: float  # arc length over which the radius drifts between its extremes
    fold_period: tuple[float, float]  # distance between haustral folds
    fold_depth: tuple[float, float]  # ridge height as a fraction of the radius
    fold_width: float  # axial extent of one fold ridge
    curvature: float  # largest centreline curvature (1/cm); keep 1/curvature > 2 * radius
    bend_spacing: float  # distance between bend joints in the flat parts


@dataclass
class Tube:
    """Slab arrays of a tube (float64 numpy, world frame, cm). ``J`` segments, ``J + 1`` joints."""

    joints: np.ndarray  # [J+1, 3] c_j
    normals: np.ndarray  # [J+1, 3] joint plane normals n_j (pointing forward)
    arc: np.ndarray  # [J+1] arc length of each joint
    directions: np.ndarray  # [J, 3] u_j
    lengths: np.ndarray  # [J] L_j
    radii: np.ndarray  # [J] r_j (radius at the segment's first joint)
    slopes: np.ndarray  # [J] k_j
    e1: np.ndarray  # [J, 3] transported frame, angle 0
    e2: np.ndarray  # [J, 3] u_j x e1_j, angle pi/2

    @property
    def length(self) -> float:
        return float(self.arc[-1])

    @property
    def wall_arc(self) -> np.ndarray:
        """``[J+1]`` length along the wall's profile (slanted fold faces count in full) at each joint."""
        return np.concatenate([[0.0], np.cumsum(self.lengths * np.sqrt(1 + self.slopes**2))])

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> "Tube":
        """The same tube moved rigidly by ``x -> rotation @ x + translation``."""
        turn = lambda v: v @ rotation.T  # noqa: E731
        return Tube(
            joints=turn(self.joints) + translation,
            normals=turn(self.normals),
            arc=self.arc,
            directions=turn(self.directions),
            lengths=self.lengths,
            radii=self.radii,
            slopes=self.slopes,
            e1=turn(self.e1),
            e2=turn(self.e2),
        )

    def radius_at(self, arc: np.ndarray) -> np.ndarray:
        """Wall radius (cm) at arc lengths ``arc`` (piecewise linear, as the slabs are)."""
        ends = self.radii + self.slopes * self.lengths
        knots = np.concatenate([self.radii, ends[-1:]])
        return np.interp(arc, self.arc, knots)

    def centreline_at(self, arc: np.ndarray) -> np.ndarray:
        """Points ``[N, 3]`` on the centreline polyline at arc lengths ``arc``."""
        return np.stack([np.interp(arc, self.arc, self.joints[:, i]) for i in range(3)], axis=-1)

    def slab_containing(self, point: np.ndarray) -> int:
        """Index of the slab that contains ``point`` (which must be inside the tube)."""
        side = np.einsum("jk,jk->j", point - self.joints, self.normals)
        inside = np.nonzero((side[:-1] >= 0) & (side[1:] < 0))[0]
        if len(inside) == 0:
            raise ValueError(f"point {point} lies in no slab of the tube")
        centres = self.joints[inside] + 0.5 * self.lengths[inside, None] * self.directions[inside]
        return int(inside[np.argmin(np.linalg.norm(centres - point, axis=1))])


# ------------------------------------------------------------------------------------------- build
def build_tube(shape: TubeShape, length: float, rng: np.random.Generator) -> Tube:
    """A random tube of at least ``length`` cm, starting at the origin along +z."""
    pieces = _profile_pieces(shape, length, rng)
    lengths = np.array([p[0] for p in pieces])
    radii = np.array([p[1] for p in pieces])
    ends = np.array([p[2] for p in pieces])
    bend_share = np.array([p[3] for p in pieces])
    arc = np.concatenate([[0.0], np.cumsum(lengths)])
    bend = _bend_field(shape, rng)

    count = len(pieces)
    directions = np.zeros((count, 3))
    e1 = np.zeros((count, 3))
    u = np.array([0.0, 0.0, 1.0])
    x = np.array([1.0, 0.0, 0.0])
    for j in range(count):
        if bend_share[j] > 0:
            axis_angle = bend(arc[j], x, np.cross(u, x)) * bend_share[j]
            # Keep the two planes of every slab from meeting inside the tube (they meet about
            # L / (tan(a/2) + tan(b/2)) from the axis): then the slabs tile the lumen.
            limit = min(lengths[j - 1], lengths[j]) / (SLAB_MARGIN * radii[j])
            angle = np.linalg.norm(axis_angle)
            turn = _rotation(axis_angle * min(1.0, limit / angle) if angle > 0 else axis_angle)
            u, x = turn @ u, turn @ x
        directions[j], e1[j] = u, x
    joints = np.concatenate([[np.zeros(3)], np.cumsum(lengths[:, None] * directions, axis=0)])
    normals = np.concatenate([directions[:1], directions[:-1] + directions[1:], directions[-1:]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return Tube(
        joints=joints,
        normals=normals,
        arc=arc,
        directions=directions,
        lengths=lengths,
        radii=radii,
        slopes=(ends - radii) / lengths,
        e1=e1,
        e2=np.cross(directions, e1),
    )


def _profile_pieces(shape: TubeShape, length: float, rng: np.random.Generator) -> list[tuple]:
    """Segments as ``(length, start radius, end radius, arc length of bending at its first joint)``.

    Each haustral period is a fold (straight run of cones: the radius dips to a ridge and recovers to the
    next period's radius) followed by a flat cylindrical stretch; the bending of the whole period is
    shared among the inner joints of the flat stretch (joints between two equal cylinders).
    """
    phase = rng.uniform(0, 2 * np.pi, size=2)
    low, high = shape.radius

    def radius(s: float) -> float:
        wave = 0.6 * np.sin(2 * np.pi * s / shape.radius_wavelength + phase[0])
        wave += 0.4 * np.sin(2 * np.pi * s / (0.37 * shape.radius_wavelength) + phase[1])
        return low + (high - low) * (0.5 + 0.5 * wave)

    # A fold is a smooth bump (zero slope at both ends and at the crest) on a smooth step between the two
    # flat radii, sampled by FOLD_PIECES cones; shading normals hide the creases between them.
    ridge_at = np.linspace(0.0, 1.0, FOLD_PIECES + 1)
    ridge_height = np.sin(np.pi * ridge_at) ** 2
    ridge_step = ridge_at * ridge_at * (3 - 2 * ridge_at)

    r_flat = radius(0.0)
    pieces: list[tuple] = [(1.0, r_flat, r_flat, 0.0)]  # a straight lead-in before the first fold
    s = 1.0
    while s < length:
        period = rng.uniform(*shape.fold_period)
        r_next = radius(s + period)
        height = rng.uniform(*shape.fold_depth) * min(r_flat, r_next)
        profile = r_flat + (r_next - r_flat) * ridge_step - height * ridge_height
        steps = np.diff(ridge_at) * shape.fold_width
        for step, r0, r1 in zip(steps, profile[:-1], profile[1:]):
            pieces.append((step, r0, r1, 0.0))
        flat = max(period - shape.fold_width, 2 * shape.bend_spacing)
        count = max(int(round(flat / shape.bend_spacing)), 2)
        share = (shape.fold_width + flat) / (count - 1)
        for i in range(count):
            pieces.append((flat / count, r_next, r_next, share if i > 0 else 0.0))
        s += shape.fold_width + flat
        r_flat = r_next
    return pieces


def _bend_field(shape: TubeShape, rng: np.random.Generator):
    """Smooth random curvature vector (axis-angle per cm) in the local frame, as a function of arc length."""
    freqs = rng.uniform(0.01, 0.05, size=(2, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(2, 3))
    weights = rng.uniform(0.5, 1.0, size=(2, 3))
    weights /= weights.sum(axis=1, keepdims=True)

    def bend(s: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        a, b = (weights * np.sin(2 * np.pi * freqs * s + phases)).sum(axis=1)
        strength = max(1.0, float(np.hypot(a, b)))  # never above shape.curvature
        return shape.curvature * (a * x + b * y) / strength

    return bend


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    """Rodrigues' formula (numpy float64)."""
    angle = float(np.linalg.norm(axis_angle))
    if angle < 1e-12:
        return np.eye(3)
    k = axis_angle / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


# ----------------------------------------------------------------------------------- intersection
@dataclass
class Hits:
    """Where rays meet the tube: ``t`` [N] (z-depth for unnormalised rays), ``slab`` [N] (-1: the cap)."""

    t: torch.Tensor
    slab: torch.Tensor


@dataclass
class TubeView:
    """Slabs ``first .. cap-1`` of a tube relative to a camera centre (float32 torch, on the render device).

    ``table`` holds one row of per-slab constants (columns :data:`COLUMNS`) so that per-ray lookups are a
    single ``index_select``.
    """

    joints: torch.Tensor  # [S+1, 3] c_j - o
    normals: torch.Tensor  # [S+1, 3]
    directions: torch.Tensor  # [S, 3]
    lengths: torch.Tensor  # [S]
    radii: torch.Tensor  # [S]
    slopes: torch.Tensor  # [S]
    cap_wall: float  # wall profile length at the cap joint
    table: torch.Tensor  # [S, len(COLUMNS)]
    ring_forms: torch.Tensor  # [S+1, 6] see _ring_forms (row 0 unused)
    first: int  # index of slab 0 of this view in the whole tube
    camera: int  # slab of this view that contains the camera


# Per-slab constants, camera at the origin: joint c, axis u, plane normals n0 (own joint), n1 (next joint),
# transported frame e1 / e2, c.u, c.c, radius, slope, signed origin-to-plane distances, wall profile
# length at the joint and across the slab.
COLUMNS = (
    "cx cy cz ux uy uz n0x n0y n0z n1x n1y n1z e1x e1y e1z e2x e2y e2z "
    "c_u c_c radius slope side0 side1 wall wall_length"
).split()
_COL = {name: i for i, name in enumerate(COLUMNS)}


def tube_view(tube: Tube, origin: np.ndarray, first: int, cap: int, device: torch.device) -> TubeView:
    """Slabs ``first .. cap - 1`` around ``origin``; the joint plane ``cap`` closes the tube."""
    camera = tube.slab_containing(origin)
    if not 0 <= first <= camera < cap <= len(tube.lengths):
        raise ValueError(f"slab range {first}..{cap} must lie in the tube's {len(tube.lengths)} and hold {camera}")
    joints = tube.joints[first : cap + 1] - origin
    normals = tube.normals[first : cap + 1]
    c, n0, n1 = joints[:-1], normals[:-1], normals[1:]
    u = tube.directions[first:cap]
    table = np.concatenate(
        [
            c,
            u,
            n0,
            n1,
            tube.e1[first:cap],
            tube.e2[first:cap],
            np.stack(
                [
                    (c * u).sum(-1),
                    (c * c).sum(-1),
                    tube.radii[first:cap],
                    tube.slopes[first:cap],
                    -(c * n0).sum(-1),
                    -(joints[1:] * n1).sum(-1),
                    tube.wall_arc[first:cap],
                    tube.lengths[first:cap] * np.sqrt(1 + tube.slopes[first:cap] ** 2),
                ],
                axis=-1,
            ),
        ],
        axis=-1,
    )
    # The ring of joint p is the end of segment p - 1 (on a joint plane both neighbours agree).
    rings = tube.radii[first:cap] + tube.slopes[first:cap] * tube.lengths[first:cap]
    f32 = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32, device=device)  # noqa: E731
    return TubeView(
        joints=f32(joints),
        normals=f32(normals),
        directions=f32(u),
        lengths=f32(tube.lengths[first:cap]),
        radii=f32(tube.radii[first:cap]),
        slopes=f32(tube.slopes[first:cap]),
        cap_wall=float(tube.wall_arc[cap]),
        table=f32(table),
        ring_forms=f32(np.concatenate([np.zeros((1, 6)), _ring_forms(joints[1:], normals[1:], u, rings)])),
        first=first,
        camera=camera - first,
    )


def slab_constants(view: TubeView, slab: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-ray copies ``{column: [N]}`` of the constants of each ray's slab."""
    rows = view.table.index_select(0, slab).T.contiguous()
    return {name: rows[i] for i, name in enumerate(COLUMNS)}


def _dot(x: tuple[torch.Tensor, ...], g: dict[str, torch.Tensor], prefix: str) -> torch.Tensor:
    return x[0] * g[prefix + "x"] + x[1] * g[prefix + "y"] + x[2] * g[prefix + "z"]


def intersect(view: TubeView, rays: torch.Tensor) -> Hits:
    """Nearest wall hit of rays ``[N, 3]`` starting at the view's origin (inside slab ``view.camera``).

    Fast path: inside one slab the lumen is convex (the inside of a cone or cylinder between two
    planes), so a ray that is inside the wall ring at both planes of a slab does not hit that slab. The
    hit therefore lies in the slab before the first joint plane the ray crosses outside its ring, and one
    quadratic per ray finds it. Rays for which that fails (rounding at a ring, rays leaving backwards)
    take the exhaustive path: every slab in order, nearest in-slab hit. Rays inside every ring hit the
    cap plane.
    """
    if rays.ndim != 2 or rays.shape[1] != 3:
        raise ValueError(f"rays must be [N, 3], got {tuple(rays.shape)}")
    slabs = len(view.lengths)
    slab = _exit_planes(view, rays) - 1
    t = torch.full((rays.shape[0],), float("nan"), dtype=rays.dtype, device=rays.device)
    wall = torch.nonzero(slab < slabs).squeeze(1)
    t[wall] = _slab_hits(view, rays[wall], slab[wall])
    capped = slab >= slabs
    plane = view.normals[-1]
    t[capped] = (view.joints[-1] @ plane) / (rays[capped] @ plane)
    slab[capped] = -1
    retry = torch.nonzero(~torch.isfinite(t)).squeeze(1)
    if retry.numel():
        t[retry], slab[retry] = _exhaustive_hits(view, rays[retry])
    if not bool((t > 0).all()):
        raise RuntimeError("a ray left the tube without a hit: the camera is outside it or the tube is broken")
    return Hits(t=t, slab=slab)


def _exit_planes(view: TubeView, rays: torch.Tensor) -> torch.Tensor:
    """Index of the first joint plane ahead of the camera that each ray crosses outside the wall ring.

    ``len(view.lengths) + 1`` where the ray passes inside every ring including the cap's. A ray that
    cannot reach a plane going forward counts as outside it. The test is one matrix product per chunk of
    planes: see :func:`_ring_forms`.
    """
    last = len(view.lengths)
    exit_plane = torch.full((rays.shape[0],), last + 1, dtype=torch.long, device=rays.device)
    active = torch.arange(rays.shape[0], device=rays.device)
    x, y, z = rays.T
    monomials = torch.stack([x * x, y * y, z * z, x * y, x * z, y * z], dim=-1)
    start, size = view.camera + 1, FIRST_CHUNK
    while start <= last and active.numel():
        stop = min(start + size, last + 1)
        everyone = active.numel() == rays.shape[0]
        quadratic = monomials if everyone else monomials.index_select(0, active)
        linear = rays if everyone else rays.index_select(0, active)
        outside = quadratic @ view.ring_forms[start:stop].T > 0
        towards = linear @ view.normals[start:stop].T
        if not bool((towards > 0).all()):
            outside |= towards <= 0
        found, first = torch.max(outside.view(torch.uint8), dim=1)
        found = found.bool()
        exit_plane[active[found]] = first[found] + start
        active = active[~found]
        # Most rays meet the wall within a few planes: small chunks first, larger for the lumen's rays.
        start, size = stop, 2 * size
    return exit_plane


def _ring_forms(joints: np.ndarray, normals: np.ndarray, axes: np.ndarray, rings: np.ndarray) -> np.ndarray:
    """Quadratic forms ``W_p`` (as 6 monomial weights) with ``d^T W_p d > 0`` iff ray ``d`` crosses plane p
    outside its ring (for ``d . n_p > 0``; camera at the origin).

    The crossing is ``t d`` with ``t = h / (d.n)``, ``h = n.c``; its squared distance to the axis is
    ``(t d - c)^T Q (t d - c)`` with ``Q = I - u u^T``. Multiplying ``rho^2 - r^2`` by ``(d.n)^2`` gives
    ``W = h^2 Q - h (n (Qc)^T + Qc n^T) + (c^T Q c - r^2) n n^T``. Rings are shrunk by
    :data:`RING_TOLERANCE` so that rounding errs towards "outside" (the exhaustive fallback).
    """
    forms = np.zeros((len(joints), 6))
    for p, (c, n, u, r) in enumerate(zip(joints, normals, axes, rings)):
        Q = np.eye(3) - np.outer(u, u)
        h = n @ c
        qc = Q @ c
        W = h * h * Q - h * (np.outer(n, qc) + np.outer(qc, n)) + (c @ qc - r * r * (1 - RING_TOLERANCE)) * np.outer(n, n)
        forms[p] = [W[0, 0], W[1, 1], W[2, 2], 2 * W[0, 1], 2 * W[0, 2], 2 * W[1, 2]]
    return forms


def _slab_hits(view: TubeView, rays: torch.Tensor, slab: torch.Tensor) -> torch.Tensor:
    """Nearest in-slab hit of each ray with its own slab ``slab`` (NaN where there is none)."""
    g = slab_constants(view, slab)
    d = rays.T.contiguous()
    t = _nearest_root(
        a_d=_dot(d, g, "u"),
        e_d=-_dot(d, g, "c"),
        d_d=d[0] * d[0] + d[1] * d[1] + d[2] * d[2],
        d0=_dot(d, g, "n0"),
        d1=_dot(d, g, "n1"),
        c_u=g["c_u"],
        c_c=g["c_c"],
        radius=g["radius"],
        slope=g["slope"],
        side0=g["side0"],
        side1=g["side1"],
    )
    return torch.where(torch.isfinite(t), t, torch.nan)


def _exhaustive_hits(view: TubeView, rays: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest in-slab hit over all slabs (in chunks, in order), else the cap: ``(t, slab or -1)``."""
    count = rays.shape[0]
    t_all = torch.full((count,), float("nan"), dtype=rays.dtype, device=rays.device)
    slab_all = torch.full((count,), -1, dtype=torch.long, device=rays.device)
    active = torch.arange(count, device=rays.device)
    slabs = len(view.lengths)
    for start in range(0, slabs, PLANES_PER_CHUNK):
        if active.numel() == 0:
            break
        stop = min(start + PLANES_PER_CHUNK, slabs)
        c, u, n = view.joints[start:stop], view.directions[start:stop], view.normals[start : stop + 1]
        d = rays[active]
        best = _nearest_root(
            a_d=d @ u.T,
            e_d=-(d @ c.T),
            d_d=(d * d).sum(-1, keepdim=True),
            d0=d @ n[:-1].T,
            d1=d @ n[1:].T,
            c_u=(c * u).sum(-1),
            c_c=(c * c).sum(-1),
            radius=view.radii[start:stop],
            slope=view.slopes[start:stop],
            side0=-(c * n[:-1]).sum(-1),
            side1=-(view.joints[start + 1 : stop + 1] * n[1:]).sum(-1),
        )
        t, local = best.min(dim=1)
        found = torch.isfinite(t)
        t_all[active[found]] = t[found]
        slab_all[active[found]] = local[found] + start
        active = active[~found]
    if active.numel():
        plane = view.normals[-1]
        t_all[active] = (view.joints[-1] @ plane) / (rays[active] @ plane)
    return t_all, slab_all


def _nearest_root(
    a_d: torch.Tensor,
    e_d: torch.Tensor,
    d_d: torch.Tensor,
    d0: torch.Tensor,
    d1: torch.Tensor,
    c_u: torch.Tensor,
    c_c: torch.Tensor,
    radius: torch.Tensor,
    slope: torch.Tensor,
    side0: torch.Tensor,
    side1: torch.Tensor,
) -> torch.Tensor:
    """Smallest positive root of ray/cone that lies inside the slab (``inf`` where none); broadcasts.

    Camera at the origin, joint ``c``, axis ``u``, cone ``|p - c - a u| = r + k a`` with ``a = (p - c).u``.
    Along ``p = t d`` this is ``A t^2 + 2 B t + C = 0`` with, writing ``a_e = -c.u`` and ``r_e = r + k a_e``:
    ``A = d.d - (1 + k^2)(d.u)^2``, ``B = -d.c - (d.u)(a_e + k r_e)``, ``C = c.c - a_e^2 - r_e^2``.
    ``d0``, ``d1``: ray . plane normals; ``side0``, ``side1``: signed distances of the origin to the planes.
    """
    a_e = -c_u
    r_e = radius + slope * a_e
    const = c_c - a_e * a_e - r_e * r_e
    quad = d_d - (1 + slope * slope) * a_d * a_d
    half = e_d - a_d * (a_e + slope * r_e)
    disc = half * half - quad * const
    root = torch.sqrt(disc.clamp_min(0))
    # Stable pair of roots: q = -(B + sign(B) sqrt(disc)); t1 = q / A, t2 = C / q.
    q = -(half + torch.where(half >= 0, root, -root))
    best = torch.full_like(quad, float("inf"))
    for t in (q / quad, const / q):
        ok = (disc >= 0) & (t > NEAREST_HIT_CM)
        ok &= side0 + t * d0 >= -PLANE_TOLERANCE_CM
        ok &= side1 + t * d1 <= PLANE_TOLERANCE_CM
        ok &= r_e + slope * t * a_d > 0
        best = torch.where(ok & (t < best), t, best)
    return best


# ---------------------------------------------------------------------------------- surface frame
@dataclass
class SurfacePoints:
    """Hit points (camera-relative), unit normals facing the camera, and texture coordinates."""

    points: torch.Tensor  # [N, 3]
    normals: torch.Tensor  # [N, 3] the wall's own (one cone's) normals
    shading_normals: torch.Tensor  # [N, 3] continuous across joints: see _blended_frame
    arc: torch.Tensor  # [N] cm along the wall's profile (texture row coordinate)
    angle: torch.Tensor  # [N] radians in [-pi, pi]
    along: torch.Tensor  # [N, 3] unit direction of growing arc (the axis, blended across joints like the normals)
    # [N, 3] direction of growing angle: along x the cone's radial direction (unit up to the small angle between
    # the blended and the cone's own axis)
    around: torch.Tensor


def surface_points(view: TubeView, rays: torch.Tensor, hits: Hits) -> SurfacePoints:
    """Geometry and texture coordinates at the hits (cap hits: the cap plane, arc of the cap joint)."""
    wall = hits.slab >= 0
    # Cap points take their angle around the last segment's axis.
    slab = torch.where(wall, hits.slab, torch.full_like(hits.slab, len(view.lengths) - 1))
    g = slab_constants(view, slab)
    p = tuple(rays.T * hits.t)
    cone_normal, radial, distance = _cone_normal(p, g)
    normal = torch.where(wall[:, None], torch.stack(cone_normal, -1), -view.normals[-1])
    angle = torch.atan2(_dot(radial, g, "e2"), _dot(radial, g, "e1"))
    # Profile length interpolated between the joint planes (continuous across joints, unlike a projection).
    before = _dot(p, g, "n0") + g["side0"]
    after = _dot(p, g, "n1") + g["side1"]
    fraction = (before / (before - after).clamp_min(1e-9)).clamp(0, 1)
    # The cap is textured as if the wall continued radially inwards (arc grows with distance from the axis).
    arc = torch.where(wall, g["wall"] + fraction * g["wall_length"], view.cap_wall + distance)
    shading, along = _blended_frame(view, p, slab, g, fraction, normal)
    shading = torch.where(wall[:, None], shading, normal)
    around = torch.linalg.cross(along, torch.stack(radial, -1))
    return SurfacePoints(
        points=torch.stack(p, -1),
        normals=normal,
        shading_normals=shading,
        arc=arc,
        angle=angle,
        along=along,
        around=around,
    )


def _cone_normal(
    p: tuple[torch.Tensor, ...], g: dict[str, torch.Tensor]
) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...], torch.Tensor]:
    """Inward unit normal of each ray's cone ``g`` at points ``p``, the unit radial direction, and the distance
    of ``p`` from the cone's axis."""
    rel = (p[0] - g["cx"], p[1] - g["cy"], p[2] - g["cz"])
    a = _dot(rel, g, "u")
    radial = (rel[0] - a * g["ux"], rel[1] - a * g["uy"], rel[2] - a * g["uz"])
    distance = torch.sqrt(radial[0] ** 2 + radial[1] ** 2 + radial[2] ** 2)
    scale = 1 / distance.clamp_min(1e-9)
    radial = tuple(r * scale for r in radial)
    k = g["slope"]
    norm = torch.rsqrt(1 + k * k)
    normal = tuple((k * g[axis] - r) * norm for axis, r in zip(("ux", "uy", "uz"), radial))
    return normal, radial, distance


def _blended_frame(
    view: TubeView,
    p: tuple[torch.Tensor, ...],
    slab: torch.Tensor,
    g: dict[str, torch.Tensor],
    fraction: torch.Tensor,
    normal: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Shading normals and axis directions ``[N, 3]`` that are continuous across joint planes (Phong shading
    along the tube): on joint plane ``j`` both neighbouring cones shade with the mean of their normals at the
    point, and across a slab the value moves linearly from its first plane's mean to its second's.
    """
    last = len(view.lengths) - 1
    previous = slab_constants(view, (slab - 1).clamp_min(0))
    following = slab_constants(view, (slab + 1).clamp_max(last))
    axis = lambda c: torch.stack([c["ux"], c["uy"], c["uz"]], -1)  # noqa: E731
    normal_before = torch.stack(_cone_normal(p, previous)[0], -1)
    normal_after = torch.stack(_cone_normal(p, following)[0], -1)
    weight = fraction[:, None]
    shading = (1 - weight) * (normal_before + normal) + weight * (normal + normal_after)
    along = (1 - weight) * (axis(previous) + axis(g)) + weight * (axis(g) + axis(following))
    return shading / shading.norm(dim=-1, keepdim=True), along / along.norm(dim=-1, keepdim=True)
