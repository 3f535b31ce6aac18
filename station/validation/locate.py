"""Finding the artefact in a cloud, its fit, and the pose refinement by analysis by synthesis.

An artefact's *fit* is what a cloud says of its pose: a sphere's centre, a ball bar's two
centres, a CAD part's ICP pose. ``locate`` finds it with no prior but the nominal size;
``fit_near`` refits it near a known pose (points within ``SHELL_MM`` of the surface).
``refine_pose`` moves the virtual artefact until the twin's cloud fits where the real cloud
fits: ``pose_{k+1} = pose_k + (fit(real) - fit(virtual(pose_k)))``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Generic, Protocol, TypeVar

import numpy as np

from station.validation.folder import (
    AnyArtefact,
    BallBarArtefact,
    CadArtefact,
    Pose,
    RealScanError,
    SphereArtefact,
)

if TYPE_CHECKING:
    from trimesh import Trimesh

    from sim.fpp.cloud import PointCloud

SHELL_MM = 2.0  # points this close to a located ball go to its fit
MIN_BALL_POINTS = 20
CONVERGED_MM = 1e-3  # the refinement stops when its correction is below 1 um
MAX_REFINE = 8


@dataclass(frozen=True)
class ArtefactFit:
    """What one cloud says of the artefact: ``centres`` (k, 3) mm (a sphere's, a ball bar's
    two, or a CAD part's origin), ``radii`` (k,) mm, ``pose`` (world from object), ``size_mm``
    (diameter, centre distance; NaN for a CAD part), ``rms_mm`` (fit RMS), ``kept`` per ball
    the pixel keys of the points the fit kept, ``pose_centres`` (k, 3) the centres with each
    ball's radius held at its nominal value (what the pose refinement compares: a cap seen
    from one side trades centre depth for radius when both are free)."""

    centres: np.ndarray
    radii: np.ndarray
    pose: Pose
    size_mm: float
    rms_mm: float
    kept: tuple[np.ndarray, ...] = field(default=())
    pose_centres: np.ndarray | None = None


def pixel_keys(cloud: PointCloud) -> np.ndarray:
    """One integer per point naming its rig pixel (camera, v, u) (n,)."""
    f = cloud.fields
    return ((np.asarray(f["camera"], np.int64) * 1_000_000 + np.asarray(f["v"], np.int64))
            * 1_000_000 + np.asarray(f["u"], np.int64))


def bar_pose(c0: np.ndarray, c1: np.ndarray) -> Pose:
    """The ball bar's pose from its ball centres: origin at the midpoint, object x from ball
    0 to ball 1, object y as near world y as that allows (``BallBarObject``'s frame)."""
    x = (c1 - c0) / np.linalg.norm(c1 - c0)
    up = np.array([0.0, 1.0, 0.0]) if abs(x[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    z = np.cross(x, up)
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    return Pose(R=tuple(map(tuple, R.tolist())), t=tuple(((c0 + c1) / 2).tolist()))


def ball_centres(artefact: AnyArtefact, pose: Pose) -> np.ndarray:
    """The artefact's ball centres (k, 3) mm at ``pose``."""
    t = np.asarray(pose.t)
    if isinstance(artefact, BallBarArtefact):
        half = artefact.centre_distance_mm / 2
        R = np.asarray(pose.R)
        return np.stack([t + R @ [-half, 0, 0], t + R @ [half, 0, 0]])
    return t[None, :]


def _fit_balls(cloud: PointCloud, artefact: SphereArtefact | BallBarArtefact,
               centres: np.ndarray, name: str) -> ArtefactFit:
    from sim.metrology.spheres import fit_sphere

    pts = np.asarray(cloud.points, np.float64)
    keys = pixel_keys(cloud)
    r = (artefact.diameter_mm if isinstance(artefact, SphereArtefact)
         else artefact.ball_diameter_mm) / 2
    fits, kept, fixed = [], [], []
    for k, c in enumerate(centres):
        near = np.abs(np.linalg.norm(pts - c, axis=1) - r) < SHELL_MM
        if near.sum() < MIN_BALL_POINTS:
            raise RealScanError(f"position {name}: only {int(near.sum())} points near ball "
                                f"{k + 1}; the artefact is not where it was found")
        f = fit_sphere(pts[near])
        fits.append(f)
        kept.append(keys[near][f.inliers])
        fixed.append(fixed_radius_centre(pts[near][f.inliers], f.centre, r))
    cs = np.stack([f.centre for f in fits])
    fc = np.stack(fixed)
    if isinstance(artefact, SphereArtefact):
        pose, size = Pose(t=tuple(fc[0].tolist())), float(fits[0].diameter)
    else:
        pose, size = bar_pose(fc[0], fc[1]), float(np.linalg.norm(cs[1] - cs[0]))
    return ArtefactFit(cs, np.array([f.radius for f in fits]), pose, size,
                       float(max(f.rms for f in fits)), tuple(kept), fc)


def fixed_radius_centre(points: np.ndarray, start: np.ndarray, radius_mm: float,
                        iterations: int = 20) -> np.ndarray:
    """The centre (3,) mm of the sphere of radius ``radius_mm`` nearest the points (n, 3) in
    the least-squares sense (Gauss-Newton from ``start``)."""
    c = np.asarray(start, np.float64).copy()
    p = np.asarray(points, np.float64)
    for _ in range(iterations):
        d = p - c
        n = np.linalg.norm(d, axis=1)
        res = n - radius_mm
        step, *_ = np.linalg.lstsq(-d / n[:, None], -res, rcond=None)  # d(res)/dc = -u
        c = c + step
        if np.linalg.norm(step) < 1e-9:
            break
    return c


def locate(cloud: PointCloud, artefact: AnyArtefact, name: str, mesh: Trimesh | None = None
           ) -> ArtefactFit:
    """Find the artefact in a cloud knowing only its nominal size: a sphere (RANSAC on the
    nominal radius, then a fit), a ball bar (two such balls, ordered by world x), or a CAD
    part (``mesh`` in its object frame; the position file's rough pose, else the centroids
    aligned, then ICP on the points inside the part's box). Raises ``RealScanError`` naming
    the position when it is not found."""
    from sim.metrology.spheres import find_spheres

    pts = np.asarray(cloud.points, np.float64)
    if isinstance(artefact, (SphereArtefact, BallBarArtefact)):
        count = 1 if isinstance(artefact, SphereArtefact) else 2
        d = (artefact.diameter_mm if isinstance(artefact, SphereArtefact)
             else artefact.ball_diameter_mm)
        try:
            found = find_spheres(pts, count, d / 2)
        except ValueError as exc:
            raise RealScanError(f"position {name}: artefact not found: no "
                                f"{'sphere' if count == 1 else 'two balls'} of {d:g} mm in the "
                                f"{len(pts)} points of the real scan ({exc})") from exc
        centres = np.stack([f.centre for f in found])
        if count == 2:
            centres = centres[np.argsort(centres[:, 0])]
        return _fit_balls(cloud, artefact, centres, name)
    return _locate_cad(pts, artefact, name, mesh)


def _locate_cad(pts: np.ndarray, artefact: CadArtefact, name: str, mesh: Trimesh | None
                ) -> ArtefactFit:
    import trimesh

    from sim.metrology.compare import icp, mesh_signed_distance

    if mesh is None:
        raise TypeError("a CAD part is located with its mesh")
    start = artefact.pose or Pose(t=tuple((pts.mean(axis=0) - mesh.centroid).tolist()))
    R0, t0 = np.asarray(start.R), np.asarray(start.t)
    lo, hi = mesh.bounds
    margin = max(2.0, 0.05 * float(np.linalg.norm(hi - lo)))
    local = (pts - t0) @ R0  # into the object frame
    inside = np.all((local >= lo - margin) & (local <= hi + margin), axis=1)
    if inside.sum() < 50:
        raise RealScanError(f"position {name}: artefact not found: {int(inside.sum())} points "
                            "inside the CAD part's box at its rough pose; give artefact.pose")
    ref, face = trimesh.sample.sample_surface_even(mesh, 20000, seed=0)
    tf, it = icp(local[inside], ref, mesh.face_normals[face], max_iterations=60)
    d = mesh_signed_distance(tf.apply(local[inside]), mesh)
    rms = float(np.sqrt(np.mean(d * d)))
    # ICP can creep along a part's free directions for its whole budget with the fit already
    # good (the plate with steps: RMS 0.048 mm after 60 iterations): the fit decides
    if rms > 0.02 * float(np.linalg.norm(hi - lo)):
        raise RealScanError(f"position {name}: artefact not found: ICP onto the CAD part did "
                            f"not converge (RMS {rms:.3g} mm after {it} iterations)")
    # object -> world: x_w = R0 (tf^-1 x_o) + t0 with tf^-1 x = R^T (x - t)
    R = R0 @ tf.R.T
    t = t0 - R @ tf.t
    return ArtefactFit(t[None, :], np.zeros(1), Pose(R=tuple(map(tuple, R.tolist())),
                                                   t=tuple(t.tolist())), float("nan"), rms)


def fit_near(cloud: PointCloud, artefact: AnyArtefact, pose: Pose, name: str,
             mesh: Trimesh | None = None) -> ArtefactFit:
    """The artefact's fit in ``cloud`` near a known ``pose`` (the same rule for every
    scanner: each ball refitted to the points within ``SHELL_MM`` of it; a CAD part by ICP
    from ``pose``)."""
    if isinstance(artefact, CadArtefact):
        return _locate_cad(np.asarray(cloud.points, np.float64),
                           artefact.model_copy(update={"pose": pose}), name, mesh)
    return _fit_balls(cloud, artefact, ball_centres(artefact, pose), name)


def pose_correction(real: ArtefactFit, virtual: ArtefactFit, artefact: AnyArtefact,
                    real_cloud: PointCloud | None = None,
                    virtual_cloud: PointCloud | None = None) -> np.ndarray:
    """``fit(real) - fit(virtual)`` per centre (k, 3) mm. Balls: each ball's nominal-radius
    centre refitted in both clouds on the pixels both fits kept (given the clouds and at
    least ``MIN_BALL_POINTS`` shared pixels), so that pixels one cloud has at the limb and
    the other has not move neither fit; else the fits' own nominal-radius centres. A CAD
    part: the ICP origins."""
    if real.pose_centres is None or virtual.pose_centres is None:
        return real.centres - virtual.centres
    delta = real.pose_centres - virtual.pose_centres
    if real_cloud is None or virtual_cloud is None or isinstance(artefact, CadArtefact):
        return delta
    r = (artefact.diameter_mm if isinstance(artefact, SphereArtefact)
         else artefact.ball_diameter_mm) / 2
    pts = [np.asarray(c.points, np.float64) for c in (real_cloud, virtual_cloud)]
    keys = [pixel_keys(c) for c in (real_cloud, virtual_cloud)]
    for k, (kr, kv) in enumerate(zip(real.kept, virtual.kept, strict=True)):
        shared = np.intersect1d(kr, kv)
        if len(shared) < MIN_BALL_POINTS:
            continue
        starts = (real.pose_centres[k], virtual.pose_centres[k])
        c = [fixed_radius_centre(p[np.isin(key, shared)], start, r)
             for p, key, start in zip(pts, keys, starts, strict=True)]
        delta[k] = c[0] - c[1]
    return delta


def corrected_pose(artefact: AnyArtefact, pose: Pose, delta: np.ndarray) -> Pose:
    """``pose`` moved by the centre corrections ``delta`` (k, 3) mm: a sphere's or CAD part's
    origin translated; a ball bar's two centres each moved, the bar's length kept nominal."""
    if isinstance(artefact, BallBarArtefact):
        c = ball_centres(artefact, pose) + delta
        return bar_pose(c[0], c[1])
    return pose.model_copy(update={"t": tuple((np.asarray(pose.t) + delta[0]).tolist())})


class Scanned(Protocol):
    """What a twin's scan at a pose offers the refinement: its cloud."""

    @property
    def cloud(self) -> PointCloud: ...


S = TypeVar("S", bound=Scanned)


@dataclass
class Refinement(Generic[S]):
    """A refined pose: ``pose``, the corrections (um) of every step, whether the last was
    below ``CONVERGED_MM``, and the twin's scan at ``pose`` (``last``)."""

    pose: Pose
    steps_um: list[float]
    converged: bool
    last: S


def refine_pose(artefact: AnyArtefact, real: ArtefactFit, start: Pose,
                scan_at: Callable[[Pose], S], name: str, mesh: Trimesh | None = None,
                max_steps: int = MAX_REFINE, real_cloud: PointCloud | None = None
                ) -> Refinement[S]:
    """Analysis by synthesis: scan the artefact with the twin at ``start`` (``scan_at(pose)``
    returns an object with ``.cloud``), fit it, move the pose by ``fit(real) - fit(virtual)``
    (``pose_correction``, on shared pixels when ``real_cloud`` is given); until the pose moves
    by less than ``CONVERGED_MM``. A step is the largest move of a ball centre (or origin):
    a ball bar is rigid at its nominal length, so the part of the two balls' corrections
    that would change its length (the real and virtual length biases differ) is not a pose
    error and does not keep the iteration going. A step that does not shrink (the fit jumps
    as limb pixels come and go) is halved from the best pose so far, as often as needed.
    Returns the pose with the smallest step and the twin's scan there."""
    pose, steps = start, []
    best: tuple[float, Pose, S, np.ndarray] | None = None
    damping = 1.0
    for _ in range(max_steps):
        last = scan_at(pose)
        virt = fit_near(last.cloud, artefact, pose, name, mesh)
        delta = pose_correction(real, virt, artefact, real_cloud, last.cloud)
        size = pose_offset_um(corrected_pose(artefact, pose, delta), pose, artefact) * 1e-3
        steps.append(size * 1e3)
        if best is None or size < best[0]:
            if best is not None and size > 0.5 * best[0]:
                damping *= 0.5  # slow progress: a jumpy fit, step shorter
            best = (size, pose, last, delta)
        else:
            damping *= 0.5
        if size < CONVERGED_MM:
            return Refinement(pose, steps, True, last)
        pose = corrected_pose(artefact, best[1], damping * best[3])
    if best is None:
        raise ValueError(f"max_steps {max_steps}: the refinement needs at least one step")
    return Refinement(best[1], steps, False, best[2])


def pose_offset_um(a: Pose, b: Pose, artefact: AnyArtefact) -> float:
    """Largest distance (um) between the artefact's ball centres (or origins) at two poses."""
    return float(np.max(np.linalg.norm(ball_centres(artefact, a) - ball_centres(artefact, b),
                                       axis=1)) * 1e3)
