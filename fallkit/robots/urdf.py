"""URDF import: turn the robot description a vendor ships into a fallkit robot.

`robot_from_urdf(name, urdf, joints=..., components=...)` returns a RobotSpec;
`urdf_to_mjcf(urdf, ...)` is the conversion step alone. MuJoCo's own URDF
compiler does the work (`mujoco.MjSpec.from_string` on the URDF, then
`MjSpec.fuse_static`); this module only prepares the URDF for it and checks
what MuJoCo would reject with a message that names nothing useful:

- meshes: `package://pkg/...` (found next to the URDF's ancestors, on
  ROS_PACKAGE_PATH or in `package_dirs`), `file://` and relative paths are
  resolved; a missing collision mesh is an error. Collision meshes MuJoCo cannot
  read (anything but .stl/.obj/.msh, e.g. Collada .dae) are replaced by a
  readable file of the same name next to them if there is one, else by ONE box
  per link with the link's mass and inertia (the "equivalent inertia box"),
  with a warning. Visual elements are dropped: fallkit simulates and renders the
  collision geometry.
- inertias MuJoCo refuses (not positive definite, or violating A + B >= C) are
  replaced by the isotropic inertia of the same trace, with a warning naming
  the link. That is MuJoCo's own `balanceinertia` rule, extended to
  non-positive eigenvalues (go1's 1 mg `base` link has such an inertia).
- floating base: the root link (or `root_link`, when the URDF hangs the robot
  under dummy links joined by fixed joints) is written without joints, so
  RobotSpec adds its free joint "root".
- static links (fixed joints: sensor frames, rotor housings, feet) are fused
  into their parents by MuJoCo, except the links fallkit names (components,
  disturbance bodies, `keep_bodies`), which stay bodies.
- joint effort limits are dropped from the MJCF: the torque limit of each
  actuated joint is the one in its JointSpec (one source of truth).

The MJCF is written with its collision meshes into a content-addressed folder
of the cache (`$FALLKIT_CACHE_DIR`, else `$XDG_CACHE_HOME/fallkit`, else
`~/.cache/fallkit`): `urdf/<name>-<hash>/<name>.xml`, with mesh paths relative
to it, so the same URDF gives the same MJCF text (and `RobotSpec.model_hash`)
on every machine. Conversion takes milliseconds for primitive-only robots and
is redone on each call; an existing output folder is reused.

A URDF that cannot be used raises `URDFError` naming the file and the element.
"""

from __future__ import annotations

import hashlib
import math
import os
import shutil
import tempfile
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from fallkit.errors import RobotSpecError, URDFError
from fallkit.robots.spec import ComponentSpec, JointSpec, RobotSpec, make_robot_spec

READABLE_MESHES = (".stl", ".obj", ".msh")  # what MuJoCo's compiler reads without plugins
ACTUATED_TYPES = ("revolute", "continuous")  # URDF joints that become MuJoCo hinges
_FORMAT = 1  # bump when the conversion changes, so cached folders are not reused




class URDFWarning(UserWarning):
    """A URDF defect the importer repaired (an inertia, an unreadable mesh)."""


# ---- public API ------------------------------------------------------------------------


def robot_from_urdf(
    name: str,
    urdf: str | Path,
    *,
    joints: Iterable[JointSpec],
    components: Mapping[str, ComponentSpec] | None = None,
    nominal_pose: Mapping[str, float] | None = None,
    disturbance_bodies: Mapping[str, list[str]] | None = None,
    root_link: str | None = None,
    armature: Mapping[str, float] | None = None,
    keep_bodies: Iterable[str] = (),
    package_dirs: Mapping[str, str | Path] | None = None,
    edit: Callable[[mujoco.MjSpec], None] | None = None,
    cache_dir: str | Path | None = None,
    policy_hz: float = 50.0,
    timestep: float = 0.005,
    friction: float = 1.0,
) -> RobotSpec:
    """A RobotSpec for the robot described by `urdf`.

    joints: the actuated joints in policy order, with PD gains and torque
        limits; each must be a revolute or continuous joint of the URDF.
    components: named groups of links with sensitivity weights; default: one
        component "body" holding every body of the converted model, weight 1.
    armature: joint -> reflected rotor inertia [kg·m²] (URDF has no such field).
    edit: called with the MjSpec of the imported robot before static links are
        fused, to add what the URDF lacks (geoms, sites) with MuJoCo's own API.
    The other arguments are RobotSpec's fields or `urdf_to_mjcf`'s.
    """
    path = Path(urdf)
    joints = list(joints)
    tree = _read_urdf(path)
    movable = {n: j.get("type") for n, j in tree.joints.items()}
    for j in joints:
        if j.name not in movable:
            raise URDFError(
                f"{path}: joints: no joint '{j.name}' in the URDF; its revolute joints are "
                f"{sorted(n for n, t in movable.items() if t in ACTUATED_TYPES)}"
            )
        if movable[j.name] not in ACTUATED_TYPES:
            raise URDFError(
                f"{path}: joints: joint '{j.name}' is {movable[j.name]}; only revolute and continuous joints can be actuated"
            )
    named = {b: "keep_bodies" for b in keep_bodies}
    for role, bodies in (disturbance_bodies or {}).items():
        named.update({b: f"disturbance_bodies.{role}" for b in bodies})
    for comp, c in (components or {}).items():
        named.update({b: f"components.{comp}" for b in c.bodies})
    mjcf = _convert(path, tree, root_link, named, armature, package_dirs, edit, cache_dir, name)
    spec = mujoco.MjSpec.from_file(str(mjcf))
    root = _root_body(spec)
    if components is None:
        components = {"body": ComponentSpec(bodies=[b.name for b in spec.bodies if b.name != "world"], weight=1.0)}
    return make_robot_spec(
        name,
        mjcf=mjcf,
        root_body=root,
        joints=joints,
        components=dict(components),
        nominal_pose=dict(nominal_pose or {}),
        disturbance_bodies=dict(disturbance_bodies or {}),
        policy_hz=policy_hz,
        timestep=timestep,
        friction=friction,
    )


def urdf_to_mjcf(
    urdf: str | Path,
    *,
    root_link: str | None = None,
    keep_bodies: Iterable[str] = (),
    armature: Mapping[str, float] | None = None,
    package_dirs: Mapping[str, str | Path] | None = None,
    edit: Callable[[mujoco.MjSpec], None] | None = None,
    cache_dir: str | Path | None = None,
    name: str | None = None,
) -> Path:
    """Convert `urdf` to an MJCF of the robot alone (no floor, actuators or free joint).

    Returns the path of the MJCF in the cache; see the module docstring for
    what is resolved, repaired or refused.
    """
    path = Path(urdf)
    named = {b: "keep_bodies" for b in keep_bodies}
    return _convert(path, _read_urdf(path), root_link, named, armature, package_dirs, edit, cache_dir, name)


def _convert(
    path: Path,
    tree: "_Urdf",
    root_link: str | None,
    named: dict[str, str],
    armature: Mapping[str, float] | None,
    package_dirs: Mapping[str, str | Path] | None,
    edit: Callable[[mujoco.MjSpec], None] | None,
    cache_dir: str | Path | None,
    name: str | None,
) -> Path:
    """URDF tree -> MJCF file; `named`: bodies to keep -> where they were named (for errors)."""
    root = _choose_root(tree, root_link)
    _prepare(tree, root, {k: Path(v) for k, v in (package_dirs or {}).items()})
    xml = ET.tostring(tree.root, encoding="unicode")
    try:
        spec = mujoco.MjSpec.from_string(xml)
    except Exception as exc:
        raise URDFError(f"{path}: MuJoCo cannot read it: {_one_line(exc)}") from None

    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    for joint in spec.joints:  # torque limits live in the JointSpecs
        joint.actfrclimited = mujoco.mjtLimited.mjLIMITED_FALSE
        joint.actfrcrange = [0.0, 0.0]
    for jname, value in (armature or {}).items():
        joint = spec.joint(jname)
        if joint is None:
            raise URDFError(f"{path}: armature: no joint '{jname}' in the URDF")
        joint.armature = float(value)
    if edit is not None:
        edit(spec)

    for body, where in named.items():
        if spec.body(body) is None:
            known = sorted(b.name for b in spec.bodies if b.name != "world")
            raise URDFError(f"{path}: {where}: no link '{body}' in the URDF (links: {', '.join(known)})")
    _fuse_static(spec, path, root, [root, *named])
    return _write(spec, path, name or tree.name, tree.notes, cache_dir)


# ---- reading and preparing the URDF -----------------------------------------------------


@dataclass
class _Urdf:
    path: Path
    root: ET.Element
    name: str
    links: dict[str, ET.Element]
    joints: dict[str, ET.Element]
    parent_of: dict[str, str] = field(default_factory=dict)  # child link -> joint name
    notes: list[str] = field(default_factory=list)  # repairs, written into the MJCF header

    def warn(self, message: str) -> None:
        self.notes.append(message)
        warnings.warn(f"{self.path}: {message}", URDFWarning, stacklevel=4)


def _read_urdf(path: Path) -> _Urdf:
    if not path.is_file():
        raise URDFError(f"{path}: URDF file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        line, col = exc.position
        raise URDFError(f"{path}:{line}:{col}: malformed XML: {str(exc).split(':')[0]}") from None
    if root.tag != "robot":
        raise URDFError(f"{path}: not a URDF: the root element is <{root.tag}>, expected <robot>")
    links: dict[str, ET.Element] = {}
    for link in root.findall("link"):
        lname = link.get("name")
        if not lname:
            raise URDFError(f"{path}: a <link> has no name")
        if lname in links:
            raise URDFError(f"{path}: link '{lname}' is defined twice")
        links[lname] = link
    if not links:
        raise URDFError(f"{path}: the URDF defines no <link>")
    tree = _Urdf(path, root, root.get("name") or path.stem, links, {})
    for joint in root.findall("joint"):
        jname = joint.get("name") or "?"
        parent, child = joint.find("parent"), joint.find("child")
        for role, el in (("parent", parent), ("child", child)):
            if el is None or el.get("link") not in links:
                got = None if el is None else el.get("link")
                raise URDFError(f"{path}: joint '{jname}': {role} link {got!r} is not a <link> of the URDF")
        if child.get("link") in tree.parent_of:
            raise URDFError(f"{path}: joint '{jname}': link '{child.get('link')}' has two parent joints")
        tree.joints[jname] = joint
        tree.parent_of[child.get("link")] = jname
    return tree


def _choose_root(tree: _Urdf, root_link: str | None) -> str:
    """The link that gets the free joint; links above it (dummy frames) are removed."""
    tops = [n for n in tree.links if n not in tree.parent_of]
    if len(tops) != 1:
        raise URDFError(f"{tree.path}: the links must form one tree; root links found: {tops or 'none (a cycle)'}")
    top = tops[0]
    if root_link is None:
        # A "world" link is a fixed-base convention; the robot is what hangs below it.
        children = [n for n, j in tree.parent_of.items() if tree.joints[j].find("parent").get("link") == top]
        root_link = children[0] if top == "world" and len(children) == 1 else top
    if root_link not in tree.links:
        raise URDFError(f"{tree.path}: root_link: no link '{root_link}' in the URDF")
    dropped, link = [], root_link
    while link != top:
        jname = tree.parent_of[link]
        joint = tree.joints[jname]
        if joint.get("type") not in ("fixed", "floating"):
            raise URDFError(
                f"{tree.path}: root_link '{root_link}': joint '{jname}' above it is {joint.get('type')}; "
                "only fixed (or floating) joints can be replaced by the floating base"
            )
        parent = joint.find("parent").get("link")
        others = [c for c, j in tree.parent_of.items() if c != link and tree.joints[j].find("parent").get("link") == parent]
        if others:
            raise URDFError(
                f"{tree.path}: root_link '{root_link}': link '{parent}' above it also carries {others}; "
                "choose a root_link that has the whole robot below it"
            )
        tree.root.remove(joint)
        del tree.joints[jname], tree.parent_of[link]
        dropped.append(parent)
        link = parent
    for lname in dropped:
        mass = _mass(tree, tree.links[lname])
        if mass >= 1e-3:
            tree.warn(f"link '{lname}' above root_link '{root_link}' is dropped with its {mass:.3g} kg")
        tree.root.remove(tree.links.pop(lname))
    return root_link


def _prepare(tree: _Urdf, root: str, package_dirs: dict[str, Path]) -> None:
    """Resolve meshes, repair inertias and set the compiler options MuJoCo needs."""
    ext = tree.root.find("mujoco")
    if ext is None:
        ext = ET.Element("mujoco")
        tree.root.insert(0, ext)
    compiler = ext.find("compiler")
    if compiler is None:
        compiler = ET.SubElement(ext, "compiler")
    mesh_base = tree.path.parent / compiler.get("meshdir", "")
    # Absolute mesh paths from here on; fusing is done later, keeping the bodies fallkit names.
    compiler.attrib.pop("meshdir", None)
    compiler.set("strippath", "false")
    compiler.set("discardvisual", "true")
    compiler.set("fusestatic", "false")
    compiler.set("angle", "radian")

    for tag in ("gazebo", "transmission"):
        for el in tree.root.findall(tag):
            tree.root.remove(el)
    for lname, link in tree.links.items():
        for visual in link.findall("visual"):
            link.remove(visual)
        _repair_inertia(tree, lname, link)
        unreadable = []
        for collision in link.findall("collision"):
            mesh = collision.find("geometry/mesh")
            if mesh is None:
                continue
            file = _resolve_mesh(tree, lname, mesh.get("filename", ""), mesh_base, package_dirs)
            if file.suffix.lower() not in READABLE_MESHES:
                sibling = next((file.with_suffix(s) for s in READABLE_MESHES if file.with_suffix(s).is_file()), None)
                if sibling is None:
                    unreadable.append(file.name)
                    link.remove(collision)
                    continue
                file = sibling
            mesh.set("filename", str(file))
        if unreadable:
            _add_inertia_box(tree, lname, link, unreadable)


def _resolve_mesh(tree: _Urdf, link: str, filename: str, base: Path, package_dirs: dict[str, Path]) -> Path:
    where = f"link '{link}': collision mesh '{filename}'"
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://") :].partition("/")
        candidates = [package_dirs[package]] if package in package_dirs else []
        candidates += [p for p in tree.path.resolve().parents if p.name == package]
        for entry in filter(None, os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep)):
            candidates += [Path(entry) / package, Path(entry)] if Path(entry).name == package else [Path(entry) / package]
        found = next((c for c in candidates if c.is_dir()), None)
        if found is None:
            raise URDFError(
                f"{tree.path}: {where}: package '{package}' not found above the URDF or on ROS_PACKAGE_PATH; "
                f"pass package_dirs={{'{package}': <its folder>}}"
            )
        file = found / rest
    elif filename.startswith("file://"):
        file = Path(filename[len("file://") :])
    elif filename:
        file = base / filename
    else:
        raise URDFError(f"{tree.path}: {where}: <mesh> has no filename")
    if not file.is_file():
        raise URDFError(f"{tree.path}: {where}: file not found: {file}")
    return file.resolve()


def _mass(tree: _Urdf, link: ET.Element) -> float:
    el = link.find("inertial/mass")
    try:
        mass = float(el.get("value")) if el is not None else 0.0
    except (TypeError, ValueError):
        raise URDFError(f"{tree.path}: link '{link.get('name')}': <mass value> is not a number") from None
    if not math.isfinite(mass) or mass < 0:
        raise URDFError(f"{tree.path}: link '{link.get('name')}': mass {mass} must be a finite number >= 0")
    return mass


def _inertia_matrix(tree: _Urdf, lname: str, el: ET.Element) -> np.ndarray:
    try:
        v = {k: float(el.get(k, "0")) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
    except ValueError:
        raise URDFError(f"{tree.path}: link '{lname}': <inertia> has a value that is not a number") from None
    m = np.array([[v["ixx"], v["ixy"], v["ixz"]], [v["ixy"], v["iyy"], v["iyz"]], [v["ixz"], v["iyz"], v["izz"]]])
    if not np.isfinite(m).all():
        raise URDFError(f"{tree.path}: link '{lname}': <inertia> is not finite")
    return m


def _repair_inertia(tree: _Urdf, lname: str, link: ET.Element) -> None:
    mass = _mass(tree, link)
    el = link.find("inertial/inertia")
    if mass == 0 or el is None:
        return  # a massless frame: MuJoCo fuses it or reports it if it moves
    eig = np.linalg.eigvalsh(_inertia_matrix(tree, lname, el))
    if eig[0] > 1e-12 * max(eig[2], 1e-12) and eig[0] + eig[1] >= eig[2] * (1 - 1e-9):
        return
    trace = float(eig.sum())
    # MuJoCo's balanceinertia rule (same trace, all axes equal); a 1 cm sphere if there is no trace.
    value = trace / 3 if trace > 0 else 0.4 * mass * 0.01**2
    for k in ("ixy", "ixz", "iyz"):
        el.set(k, "0")
    for k in ("ixx", "iyy", "izz"):
        el.set(k, repr(value))
    tree.warn(
        f"link '{lname}': inertia is not physical (eigenvalues {', '.join(f'{e:.3g}' for e in eig)} must be "
        f"positive and satisfy A + B >= C); replaced by the isotropic inertia {value:.3g} kg·m² of the same trace"
    )


def _add_inertia_box(tree: _Urdf, lname: str, link: ET.Element, meshes: list[str]) -> None:
    """One box with the link's mass and inertia, standing in for meshes MuJoCo cannot read."""
    mass = _mass(tree, link)
    el = link.find("inertial/inertia")
    if mass <= 0 or el is None:
        tree.warn(f"link '{lname}': MuJoCo cannot read collision meshes {meshes} and the link has no mass to fit a box to; dropped")
        return
    origin = link.find("inertial/origin")
    xyz = origin.get("xyz", "0 0 0") if origin is not None else "0 0 0"
    rpy = [float(a) for a in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()]
    eig, vec = np.linalg.eigh(_inertia_matrix(tree, lname, el))  # inertia already repaired
    if np.linalg.det(vec) < 0:
        vec[:, 0] = -vec[:, 0]
    # Box of mass m with edges a,b,c: I_a = m (b² + c²) / 12, so a² = 6 (I_b + I_c - I_a) / m.
    size = [math.sqrt(max(6 * (eig.sum() - 2 * e) / mass, 1e-6)) for e in eig]
    rot = _rpy_matrix(*rpy) @ vec
    collision = ET.SubElement(link, "collision")
    ET.SubElement(collision, "origin", xyz=xyz, rpy=" ".join(repr(a) for a in _matrix_rpy(rot)))
    ET.SubElement(ET.SubElement(collision, "geometry"), "box", size=" ".join(f"{s:.6g}" for s in size))
    tree.warn(
        f"link '{lname}': MuJoCo cannot read collision meshes {meshes}; replaced by a "
        f"{' x '.join(f'{s:.3f}' for s in size)} m box with the link's mass and inertia"
    )


def _rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    """URDF rpy: fixed-axis roll (x), pitch (y), yaw (z): R = Rz(y) Ry(p) Rx(r)."""
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _matrix_rpy(m: np.ndarray) -> tuple[float, float, float]:
    pitch = math.asin(max(-1.0, min(1.0, -m[2, 0])))
    if abs(m[2, 0]) < 1 - 1e-9:
        return math.atan2(m[2, 1], m[2, 2]), pitch, math.atan2(m[1, 0], m[0, 0])
    return math.atan2(-m[1, 2], m[1, 1]), pitch, 0.0  # gimbal lock: put all of it into roll


# ---- MuJoCo side: fuse, write --------------------------------------------------------------


def _fuse_static(spec: mujoco.MjSpec, path: Path, root: str, keep: list[str]) -> None:
    """Let MuJoCo fuse static links into their parents, keeping the named ones."""
    # The root must move, or it would be fused into the world; bodies referenced by
    # an element are never fused, so each kept body gets a temporary sensor.
    free = spec.body(root).add_freejoint(name="__fallkit_root")
    temps = []
    for i, body in enumerate(dict.fromkeys(keep)):
        sensor = spec.add_sensor(name=f"__fallkit_keep{i}", type=mujoco.mjtSensor.mjSENS_CONTACT)
        sensor.objtype, sensor.objname = mujoco.mjtObj.mjOBJ_BODY, body
        sensor.intprm[0:3] = [2, 3, 1]
        temps.append(sensor)
    try:
        spec.fuse_static()
        spec.compile()  # every error MuJoCo has about the model, now, naming the URDF
    except Exception as exc:
        raise URDFError(f"{path}: MuJoCo cannot compile it: {_one_line(exc)}") from None
    for el in [*temps, free]:
        spec.delete(el)


def _write(spec: mujoco.MjSpec, path: Path, name: str, notes: list[str], cache_dir: str | Path | None) -> Path:
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
    parent = _cache_root(cache_dir) / "urdf"
    # Everything goes into a temporary folder renamed at the end: concurrent imports
    # never see half a model. Meshes are copied first: to_xml compiles, relative paths.
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=parent, prefix=f".{safe}-"))
    except OSError as exc:
        raise URDFError(f"{path}: cannot write the converted model into {parent}: {exc}; set FALLKIT_CACHE_DIR") from None
    tmp.chmod(0o755)  # mkdtemp makes it private; the cache may be shared
    try:
        digest = hashlib.sha256()
        copies: dict[str, Path] = {}
        for mesh in spec.meshes:
            src = Path(mesh.file)
            rel, k = f"meshes/{src.name}", 1
            while rel in copies and copies[rel] != src:
                rel, k = f"meshes/{src.stem}_{k}{src.suffix}", k + 1
            if rel not in copies:
                copies[rel] = src
                (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, tmp / rel)
                digest.update(rel.encode() + (tmp / rel).read_bytes())
            mesh.file = rel
        spec.modelfiledir = str(tmp)
        spec.compiler.fusestatic = False
        header = f"fallkit URDF import (format {_FORMAT}) of {path.name}: the robot only (no floor, free joint, actuators)"
        spec.comment = "\n".join([header, *(f"repaired: {n}" for n in notes)])
        xml = spec.to_xml()
        digest.update(xml.encode())
        out_dir = parent / f"{safe}-{digest.hexdigest()[:12]}"
        target = out_dir / f"{safe}.xml"
        if not target.is_file():
            (tmp / target.name).write_text(xml)
            try:
                tmp.rename(out_dir)
            except OSError:
                if not target.is_file():  # not a lost race with another process: a real failure
                    raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def _cache_root(cache_dir: str | Path | None) -> Path:
    if cache_dir is not None:
        return Path(cache_dir)
    if os.environ.get("FALLKIT_CACHE_DIR"):
        return Path(os.environ["FALLKIT_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "fallkit"


def _root_body(spec: mujoco.MjSpec) -> str:
    tops = [b for b in spec.worldbody.bodies]
    if len(tops) != 1:
        raise URDFError(f"converted model has {len(tops)} top-level bodies, expected 1")
    return tops[0].name


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())
