"""URDF side of the URDF import (`fallkit.robots.urdf`): read, check and prepare the XML.

Reading checks what the URDF must be (one tree of named links); preparing
removes the links above the floating base, resolves and replaces meshes and
repairs inertias, recording every repair as a `URDFWarning` and a note for the
MJCF header. See `fallkit.robots.urdf` for the rules.
"""

from __future__ import annotations

import math
import os
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fallkit.errors import URDFError, require_file

READABLE_MESHES = (".stl", ".obj", ".msh")  # what MuJoCo's compiler reads without plugins


class URDFWarning(UserWarning):
    """A URDF defect the importer repaired (an inertia, an unreadable mesh)."""


@dataclass
class UrdfTree:
    """A parsed URDF: its links and joints by name, and the repairs made to it."""

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


def read_urdf(path: Path) -> UrdfTree:
    """The URDF at `path`, checked to be one <robot> of uniquely named links joined by joints."""
    path = require_file(path, "URDF file", URDFError)
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
    tree = UrdfTree(path, root, root.get("name") or path.stem, links, {})
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


def choose_root(tree: UrdfTree, root_link: str | None) -> str:
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


def prepare(tree: UrdfTree, root: str, package_dirs: dict[str, Path]) -> None:
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


def _resolve_mesh(tree: UrdfTree, link: str, filename: str, base: Path, package_dirs: dict[str, Path]) -> Path:
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


def _mass(tree: UrdfTree, link: ET.Element) -> float:
    el = link.find("inertial/mass")
    try:
        mass = float(el.get("value")) if el is not None else 0.0
    except (TypeError, ValueError):
        raise URDFError(f"{tree.path}: link '{link.get('name')}': <mass value> is not a number") from None
    if not math.isfinite(mass) or mass < 0:
        raise URDFError(f"{tree.path}: link '{link.get('name')}': mass {mass} must be a finite number >= 0")
    return mass


def _inertia_matrix(tree: UrdfTree, lname: str, el: ET.Element) -> np.ndarray:
    try:
        v = {k: float(el.get(k, "0")) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
    except ValueError:
        raise URDFError(f"{tree.path}: link '{lname}': <inertia> has a value that is not a number") from None
    m = np.array([[v["ixx"], v["ixy"], v["ixz"]], [v["ixy"], v["iyy"], v["iyz"]], [v["ixz"], v["iyz"], v["izz"]]])
    if not np.isfinite(m).all():
        raise URDFError(f"{tree.path}: link '{lname}': <inertia> is not finite")
    return m


def _repair_inertia(tree: UrdfTree, lname: str, link: ET.Element) -> None:
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


def _add_inertia_box(tree: UrdfTree, lname: str, link: ET.Element, meshes: list[str]) -> None:
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

