"""The experiment's objects: positions of the spheres, ball bars and the CAD part, their
``sim`` scenes and the check that each lies inside both cameras' crops."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from station.errors import StationError
from station.experiment.config import BALLBAR_BALL_MM, BALLBAR_LENGTH_MM, ExperimentConfig

if TYPE_CHECKING:
    from trimesh import Trimesh

    from sim.optics.rig import Rig
    from sim.render.scene import Scene

@dataclass(frozen=True)
class Position:
    """One object pose: name (S1.., B1.., C1), kind ('sphere', 'ballbar', 'cad'), defocus
    group ('slight' or 'large'), world centre (3,) mm and its depth along camera 0's axis."""

    name: str
    kind: str
    defocus: str
    centre_mm: tuple[float, float, float]
    depth_mm: float


def positions(cfg: ExperimentConfig, rig: Rig) -> list[Position]:
    """Spheres (slight, then large), ball bars (slight, then large), the CAD part."""
    out = []
    groups = [("sphere", "S", "slight", cfg.sphere_slight),
              ("sphere", "S", "large", cfg.sphere_large),
              ("ballbar", "B", "slight", cfg.ballbar_slight),
              ("ballbar", "B", "large", cfg.ballbar_large)]
    if cfg.cad:
        groups.append(("cad", "C", "slight", ((cfg.cad_z_mm, 0.0),)))
    count: dict[str, int] = {}
    for kind, letter, group, items in groups:
        for z, y in items:
            count[letter] = count.get(letter, 0) + 1
            c = (0.0, float(y), float(z))
            depth = float(rig.cameras[0].to_device(np.array([c]))[0, 2])
            out.append(Position(f"{letter}{count[letter]}", kind, group, c, depth))
    return out


def cad_part_mesh(step_mm: float = 0.5) -> Trimesh:
    """The CAD part: a 120 x 80 mm plate (object frame, z towards the rig negative) with two
    steps (8 and 16 mm), two holes (12 and 8 mm diameter, 10 mm deep) and a freeform face
    (a smooth bump and saddle); a height field meshed every ``step_mm``, closed by no walls
    (the rig sees only its front)."""
    import trimesh

    xs = np.arange(-60.0, 60.0 + step_mm / 2, step_mm)
    ys = np.arange(-40.0, 40.0 + step_mm / 2, step_mm)
    X, Y = np.meshgrid(xs, ys)
    h = np.zeros_like(X)
    h[X > 20] = 8.0
    h[X > 42] = 16.0
    for cx, cy, r in ((5.0, -18.0, 6.0), (5.0, 18.0, 4.0)):
        h[(X - cx) ** 2 + (Y - cy) ** 2 < r * r] = -10.0
    free = X < -12
    u, v = (X + 36.0) / 24.0, Y / 40.0
    h[free] = (7.0 * np.exp(-(u**2 + (v / 0.6) ** 2)) + 3.0 * u * v)[free]
    verts = np.stack([X.ravel(), Y.ravel(), -h.ravel()], axis=1)
    ny, nx = X.shape
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # x right, y down: (a, c, b) winds so that the normals point towards -z (the rig)
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                            np.stack([b, c, d], -1).reshape(-1, 3)])
    return trimesh.Trimesh(verts, faces, process=False)


def scene_of(pos: Position, cfg: ExperimentConfig, cad_path: Path | None) -> Scene:
    """The ``sim`` scene of one position."""
    from sim.render.scene import BallBarObject, MeshObject, Scene, SphereObject

    obj: SphereObject | BallBarObject | MeshObject
    if pos.kind == "sphere":
        obj = SphereObject(name=pos.name, pose={"t": list(pos.centre_mm)})
    elif pos.kind == "ballbar":
        roll = cfg.ballbar_roll_deg
        if pos.defocus == "large" and cfg.ballbar_large_roll_deg is not None:
            roll = cfg.ballbar_large_roll_deg
        a = np.radians(roll)
        R = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
        obj = BallBarObject(name=pos.name, diameter_mm=BALLBAR_BALL_MM,
                            centre_distance_mm=BALLBAR_LENGTH_MM,
                            pose={"t": list(pos.centre_mm), "R": R})
    else:
        if cad_path is None:
            raise StationError(f"position {pos.name}: a CAD position needs the CAD mesh's file")
        obj = MeshObject(name=pos.name, path=cad_path, smooth_angle_deg=30.0,
                         pose={"t": list(pos.centre_mm)})
    return Scene(objects=[obj])


def view_extents_px(pos: Position, cfg: ExperimentConfig, rig: Rig,
                    cad_mesh: Trimesh | None = None) -> np.ndarray:
    """Per camera the pixel box (u0, u1, v0, v1) the position's object covers (pinhole, the
    OpenCV pixel-centre convention): its balls' surfaces, or the CAD part's bounding box
    corners (``cad_mesh``, object frame)."""
    import trimesh

    if pos.kind != "cad":
        unit = trimesh.creation.icosphere(3).vertices
        balls = scene_of(pos, cfg, None).objects[0].spheres()
        pts = np.concatenate([c[:3] + c[3] * unit for c in balls])
    else:
        lo, hi = (cad_mesh if cad_mesh is not None else cad_part_mesh()).bounds
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])
        pts = corners + np.asarray(pos.centre_mm)
    boxes = []
    for cam in rig.cameras:
        uv = cam.project(pts)
        boxes.append([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()])
    return np.asarray(boxes)


def check_views(cfg: ExperimentConfig, rig: Rig, cad_mesh: Trimesh | None = None) -> None:
    """Refuse a config with an object that does not lie wholly inside both cameras' crops
    (which would leave a scan with too few, or no, pixels seen by both cameras), naming each
    such position, its overhang and what to change."""
    w, h = cfg.camera_size
    bad = []
    for pos in positions(cfg, rig):
        for i, (u0, u1, v0, v1) in enumerate(view_extents_px(pos, cfg, rig, cad_mesh)):
            over = max(-u0, u1 - (w - 1), -v0, v1 - (h - 1))
            if over > 0:
                bad.append(f"{pos.name} ({pos.kind} at z {pos.centre_mm[2]:g} mm) overhangs "
                           f"camera {i}'s {w} x {h} crop by {over:.0f} px (u {u0:.0f}..{u1:.0f},"
                           f" v {v0:.0f}..{v1:.0f})")
    if bad:
        raise StationError("experiment config: " + "; ".join(bad) + "; move or turn the "
                           "object (sphere_*, ballbar_*, cad_z_mm) or enlarge camera_size")
