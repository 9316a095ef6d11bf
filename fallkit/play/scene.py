"""Drawing falls in the browser with viser: robots side by side, ghosts, contact-force arrows.

The browser gets only what it draws, and the geometry only once: every geom of the robot
becomes one batched mesh with an instance per strategy shown, so a frame sends poses alone —
two arrays per geom, one frame per ghost, one list of arrows. Poses come from MuJoCo's own
kinematics of the frame's qpos (one MjData per world on this side), so the browser never
simulates.

- Robots stand side by side along the world's y axis, `play.spacing` apart, in the order of the
  strategies (the first on the left, seen from the initial camera); one strategy alone sits at 0.
- The ghost is the end pose, translucent green like mode=render's: lying where the robot is,
  turned about the vertical to the robot's heading (the yaw-free goal the policy tracks, and
  how MROE compares orientations).
- Each component in contact gets one arrow: its net contact force (what the metrics measure),
  drawn from the centre of its contact points, `render.force_scale` metres per body weight.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import mujoco
import numpy as np
import torch
import trimesh
import viser
import viser.transforms as vtf

from fallkit.play.session import Frame
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import quat_conj, quat_mul, yaw_align
from fallkit.sim.base import Layout

GHOST_RGB = (64, 217, 89)  # mode=render's ghost green (fallkit.eval.render.GHOST_RGBA)
GHOST_OPACITY = 0.5
FORCE_RGB = (255, 64, 26)  # mode=render's contact-force red
PUSH_RGB = (240, 190, 20)
MIN_ARROW_FORCE = 1.0  # [N] below this a component's force is not drawn


@dataclass
class Geom:
    """One visible geom of the robot as a mesh in its own frame."""

    gid: int
    vertices: np.ndarray  # [V, 3] float32
    faces: np.ndarray  # [F, 3] uint32
    rgb: tuple[int, int, int]


def robot_geoms(model: mujoco.MjModel) -> list[Geom]:
    """Every visible geom on a moving body (not the floor), as a triangle mesh: boxes, spheres,
    capsules, cylinders, ellipsoids and meshes; MuJoCo's hidden groups (3-5) are left out."""
    out = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] == 0 or model.geom_group[g] > 2 or model.geom_rgba[g, 3] == 0:
            continue
        mesh = _mesh(model, g)
        if mesh is None:
            continue
        mat = model.geom_matid[g]
        rgba = model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[g]
        rgb = tuple(int(round(255 * c)) for c in rgba[:3])
        out.append(Geom(g, np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32), rgb))
    return out


def _mesh(model: mujoco.MjModel, g: int) -> trimesh.Trimesh | None:
    t, size, G = model.geom_type[g], model.geom_size[g], mujoco.mjtGeom
    if t == G.mjGEOM_BOX:
        return trimesh.creation.box(extents=2.0 * size)
    if t == G.mjGEOM_SPHERE:
        return trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    if t == G.mjGEOM_CAPSULE:
        return trimesh.creation.capsule(height=2.0 * size[1], radius=size[0], count=[16, 16])
    if t == G.mjGEOM_CYLINDER:
        return trimesh.creation.cylinder(radius=size[0], height=2.0 * size[1], sections=24)
    if t == G.mjGEOM_ELLIPSOID:
        return trimesh.creation.icosphere(subdivisions=2, radius=1.0).apply_scale(size)
    if t == G.mjGEOM_MESH:
        m = model.geom_dataid[g]
        va, vn, fa, fn = model.mesh_vertadr[m], model.mesh_vertnum[m], model.mesh_faceadr[m], model.mesh_facenum[m]
        return trimesh.Trimesh(model.mesh_vert[va : va + vn], model.mesh_face[fa : fa + fn], process=False)
    return None  # planes, height fields: not part of a robot


class FallScene:
    """The 3-D scene of one mode=play page (see the module docstring)."""

    def __init__(
        self, server: viser.ViserServer, spec: RobotSpec, strategies: list[str], spacing: float,
        force_scale: float, weight: float,
    ):  # fmt: skip
        self.server = server
        self.strategies = strategies
        self.spacing = spacing
        self.metres_per_newton = force_scale / weight
        self.model = spec.mj_model()
        self.layout = Layout(spec)
        self.data = [mujoco.MjData(self.model) for _ in strategies]
        self.geoms = robot_geoms(self.model)
        self.gids = np.array([g.gid for g in self.geoms])
        self.component = _geom_components(spec, self.model)
        self.shown = list(range(len(strategies)))
        self.target_quat = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
        self.show_forces = True
        self._ghosts_on = True
        self.last: Frame | None = None
        # the player's thread draws, viser's threads change what is shown: one at a time (shared MjData)
        self.lock = threading.RLock()
        self._build()

    def _build(self) -> None:
        scene, k = self.server.scene, len(self.strategies)
        scene.set_up_direction("+z")
        scene.add_grid("/ground", width=24.0, height=24.0, plane="xy", cell_size=0.25, section_size=1.0,
                       plane_color=(236, 238, 240), plane_opacity=1.0, position=(0.0, 0.0, -0.001))  # fmt: skip
        ident, zero = np.tile([1.0, 0.0, 0.0, 0.0], (k, 1)), np.zeros((k, 3))
        self.robots = [
            scene.add_batched_meshes_simple(
                f"/robots/geom{g.gid}", g.vertices, g.faces, batched_wxyzs=ident, batched_positions=zero,
                batched_colors=g.rgb, lod="off", cast_shadow=False, receive_shadow=False,
            )  # fmt: skip
            for g in self.geoms
        ]
        self.ghost_frames = [scene.add_frame(f"/ghosts/w{w}", show_axes=False) for w in range(k)]
        self.ghost_parts = [
            [
                scene.add_mesh_simple(f"/ghosts/w{w}/geom{g.gid}", g.vertices, g.faces, color=GHOST_RGB,
                                      opacity=GHOST_OPACITY, cast_shadow=False, receive_shadow=False)  # fmt: skip
                for g in self.geoms
            ]
            for w in range(k)
        ]
        self.labels = [
            scene.add_label(f"/labels/w{w}", s.replace("_", " "), font_screen_scale=1.2, anchor="bottom-center")
            for w, s in enumerate(self.strategies)
        ]
        self.arrows = scene.add_arrows("/forces", np.zeros((1, 2, 3)), FORCE_RGB, shaft_radius=0.012,
                                       head_radius=0.03, head_length=0.06, visible=False)  # fmt: skip
        self.push_arrows = scene.add_arrows("/push", np.zeros((1, 2, 3)), PUSH_RGB, shaft_radius=0.02,
                                            head_radius=0.05, head_length=0.1, visible=False)  # fmt: skip

    # ---- what is shown ---------------------------------------------------------------------

    def offset(self, w: int) -> np.ndarray:
        """Where world w is drawn: its place in the row of shown strategies."""
        j = self.shown.index(w)
        return np.array([0.0, (j - (len(self.shown) - 1) / 2) * self.spacing, 0.0])

    def set_shown(self, worlds: list[int]) -> None:
        with self.lock, self.server.atomic():
            self.shown = list(worlds)
            for w, (frame, label) in enumerate(zip(self.ghost_frames, self.labels)):
                label.visible = w in self.shown
                frame.visible = w in self.shown and self._ghosts_on
        if self.last is not None:
            self.draw(self.last)

    def show_ghosts(self, on: bool) -> None:
        self._ghosts_on = on
        for w, frame in enumerate(self.ghost_frames):
            frame.visible = on and w in self.shown

    def show_robots(self, on: bool) -> None:
        for h in self.robots:
            h.visible = on

    def set_ghost(self, qpos: np.ndarray, target_quat: np.ndarray) -> None:
        """The end pose to draw: qpos [nq] lying at the origin, and its root orientation [4]."""
        d = mujoco.MjData(self.model)
        d.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, d)
        pos = d.geom_xpos[self.gids]
        r = self.layout.root_qpos
        pos[:, :2] -= qpos[r : r + 2]  # the parent frame stands at the robot's xy
        wxyz = vtf.SO3.from_matrix(d.geom_xmat[self.gids].reshape(-1, 3, 3)).wxyz
        with self.lock:
            self.target_quat = torch.as_tensor(np.asarray(target_quat, np.float64))[None]
            with self.server.atomic():
                for parts in self.ghost_parts:
                    for h, p, q in zip(parts, pos, wxyz):
                        h.position, h.wxyz = p, q
            if self.last is not None:
                self.draw(self.last)

    # ---- one frame -----------------------------------------------------------------------

    def draw(self, frame: Frame) -> None:
        """Send one frame: the robots' geom poses, the ghosts under them, labels and arrows."""
        with self.lock:
            self._draw(frame)

    def _draw(self, frame: Frame) -> None:
        self.last = frame
        shown = self.shown
        offsets = np.stack([self.offset(w) for w in shown])
        pos, wxyz = self._geom_poses(frame.qpos, shown)
        pos += offsets[:, None, :]
        r = self.layout.root_qpos
        root = frame.qpos[shown, r : r + 3] + offsets
        turn = quat_mul(yaw_align(self.target_quat, torch.as_tensor(frame.qpos[shown, r + 3 : r + 7])),
                        quat_conj(self.target_quat)).numpy()  # fmt: skip
        arrows = self._force_arrows(frame, shown, offsets) if self.show_forces else np.zeros((0, 2, 3))
        with self.server.atomic():
            for i, h in enumerate(self.robots):
                h.batched_positions = pos[:, i].astype(np.float32)
                h.batched_wxyzs = wxyz[:, i].astype(np.float32)
            for j, w in enumerate(shown):
                self.ghost_frames[w].position = (root[j, 0], root[j, 1], 0.0)
                self.ghost_frames[w].wxyz = turn[j]
                self.labels[w].position = (root[j, 0], root[j, 1], max(root[j, 2], 0.3) + 0.55)
            self._set_arrows(self.arrows, arrows, FORCE_RGB)
            self._set_arrows(self.push_arrows, self._push_arrows(frame, root), PUSH_RGB)

    def _geom_poses(self, qpos: np.ndarray, worlds: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """World positions [k, G, 3] and orientations [k, G, 4] of the drawn geoms, and contacts
        (mj_fwdPosition runs the collision detection too when forces are drawn)."""
        k, g = len(worlds), len(self.gids)
        pos, mats = np.empty((k, g, 3)), np.empty((k, g, 9))
        for j, w in enumerate(worlds):
            d = self.data[w]
            d.qpos[:] = qpos[w]
            (mujoco.mj_fwdPosition if self.show_forces else mujoco.mj_kinematics)(self.model, d)
            pos[j], mats[j] = d.geom_xpos[self.gids], d.geom_xmat[self.gids]
        wxyz = vtf.SO3.from_matrix(mats.reshape(-1, 3, 3)).wxyz.reshape(k, g, 4)
        return pos, wxyz

    def _force_arrows(self, frame: Frame, worlds: list[int], offsets: np.ndarray) -> np.ndarray:
        """[A, 2, 3] one arrow per component in contact: from its contact points' centre along its force."""
        out = []
        for j, w in enumerate(worlds):
            d = self.data[w]
            if d.ncon == 0:
                continue
            comps = self.component[d.contact.geom[: d.ncon]].max(axis=1)  # the robot's side of each contact
            points = d.contact.pos[: d.ncon]
            for c in np.unique(comps[comps >= 0]):
                f = frame.force[w, c]
                if np.linalg.norm(f) < MIN_ARROW_FORCE:
                    continue
                base = points[comps == c].mean(axis=0) + offsets[j]
                out.append((base, base + f * self.metres_per_newton))
        return np.array(out, dtype=np.float64).reshape(-1, 2, 3)

    def _push_arrows(self, frame: Frame, root: np.ndarray) -> np.ndarray:
        """While a push acts: an arrow into each robot's root, along the push."""
        if frame.push is None or not np.linalg.norm(frame.push):
            return np.zeros((0, 2, 3))
        direction = frame.push / np.linalg.norm(frame.push)
        return np.stack([np.stack([p - 0.6 * direction, p - 0.08 * direction]) for p in root])

    @staticmethod
    def _set_arrows(handle: viser.ArrowsHandle, points: np.ndarray, rgb: tuple[int, int, int]) -> None:
        if len(points) == 0:
            handle.visible = False
            return
        handle.points = points.astype(np.float32)
        handle.colors = np.tile(np.array(rgb, np.uint8), (len(points), 1))
        handle.visible = True


def _geom_components(spec: RobotSpec, model: mujoco.MjModel) -> np.ndarray:
    """[ngeom] the component index of each geom's body, -1 for the floor and bodies of no component."""
    of_body = np.full(model.nbody, -1)
    for c, comp in enumerate(spec.components.values()):
        for body in comp.bodies:
            of_body[model.body(body).id] = c
    return of_body[model.geom_bodyid]
