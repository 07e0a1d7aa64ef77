"""The tf tree (trundle.logs.frames): chained lookups checked against poses worked out by hand,
static and dynamic edges at a time, missing frames named, configured mounts winning."""

from __future__ import annotations

import ast
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.logs import messages as m
from trundle.logs import topics
from trundle.logs.errors import DataError
from trundle.logs.frames import FrameTree, planar, quaternion_from_rpy, rotation_matrix
from trundle.logs.topics import TF_STATIC_TOPIC, TF_TOPIC

S = 1_000_000_000  # ns in a second


def planar_tf(parent: str, child: str, x: float, y: float, yaw: float, z: float = 0.0, stamp_ns: int = 0):
    return m.TFMessage((m.TransformStamped.planar(stamp_ns, parent, child, x, y, yaw, z),))


def three_hops() -> FrameTree:
    """base_link -> mast (1 m ahead, turned 90 deg left) -> laser (0.5 m along the mast's x, 0.2 m up,
    turned back 90 deg) -> tilted (0.1 m ahead, 45 deg left); and a camera at base_link's origin."""
    tree = FrameTree()
    tree.add(TF_STATIC_TOPIC, planar_tf("base_link", "mast", 1.0, 0.0, math.pi / 2))
    tree.add(TF_STATIC_TOPIC, planar_tf("mast", "laser", 0.5, 0.0, -math.pi / 2, z=0.2))
    tree.add(TF_STATIC_TOPIC, planar_tf("laser", "tilted", 0.1, 0.0, math.pi / 4))
    tree.add(TF_STATIC_TOPIC, planar_tf("base_link", "camera", 0.0, 0.0, 0.0))
    return tree


def test_a_chain_of_three_frames_gives_the_pose_worked_out_by_hand() -> None:
    tree = three_hops()
    # laser: (1, 0, 0) + Rz(90 deg) (0.5, 0, 0.2) = (1, 0.5, 0.2), yaw 90 - 90 = 0
    # tilted: laser + (0.1, 0, 0) = (1.1, 0.5, 0.2), yaw 45 deg
    pose = tree.transform("base_link", "tilted")
    np.testing.assert_allclose(pose[:3, 3], [1.1, 0.5, 0.2], atol=1e-12)
    np.testing.assert_allclose(tree.mount("tilted"), [1.1, 0.5, math.pi / 4], atol=1e-12)
    # the other way, and between two branches: the camera (at base_link's origin) seen from the laser
    np.testing.assert_allclose(tree.transform("tilted", "base_link"), np.linalg.inv(pose), atol=1e-12)
    np.testing.assert_allclose(tree.transform("laser", "camera")[:3, 3], [-1.0, -0.5, -0.2], atol=1e-12)


def test_a_missing_frame_is_a_data_error_naming_it_and_what_the_tree_holds() -> None:
    tree = three_hops()
    with pytest.raises(DataError, match=r"'front_laser' is not in the tf tree \(frames: base_link, camera, laser, "
                                        r"mast, tilted"):
        tree.mount("front_laser")
    tree.add(TF_STATIC_TOPIC, planar_tf("odom", "wheel", 0.0, 0.0, 0.0))
    with pytest.raises(DataError, match="'wheel' and 'base_link' are not connected"):
        tree.mount("wheel")
    assert tree.try_transform("base_link", "wheel") is None
    np.testing.assert_array_equal(tree.mount("front_laser", unknown_is_base=True), [0.0, 0.0, 0.0])


def test_static_edges_hold_at_any_time_and_dynamic_ones_are_interpolated() -> None:
    tree = FrameTree()
    tree.add(TF_STATIC_TOPIC, planar_tf("base_link", "laser", 0.2, 0.0, 0.0))
    tree.add(TF_TOPIC, planar_tf("odom", "base_link", 0.0, 0.0, 0.0, stamp_ns=1 * S))
    tree.add(TF_TOPIC, planar_tf("odom", "base_link", 2.0, 0.0, math.pi / 2, stamp_ns=3 * S))
    # halfway: base_link at (1, 0) heading 45 deg; the laser 0.2 m ahead of it
    half = math.pi / 4
    np.testing.assert_allclose(tree.mount("laser", "odom", 2 * S),
                               [1 + 0.2 * math.cos(half), 0.2 * math.sin(half), half],
                               atol=1e-12)
    np.testing.assert_allclose(tree.mount("laser", "base_link", 100 * S), [0.2, 0.0, 0.0])  # static: any time
    np.testing.assert_allclose(tree.mount("base_link", "odom"), [2.0, 0.0, math.pi / 2], atol=1e-12)  # latest
    expected = r"no transform odom -> base_link at 5.000 s: /tf has it from 1.000 s to 3.000 s"
    with pytest.raises(DataError, match=expected):
        tree.mount("laser", "odom", 5 * S)
    nearest = FrameTree(extrapolate_s=2.5)
    nearest.add(TF_TOPIC, planar_tf("odom", "base_link", 0.0, 0.0, 0.0, stamp_ns=1 * S))
    nearest.add(TF_TOPIC, planar_tf("odom", "base_link", 2.0, 0.0, math.pi / 2, stamp_ns=3 * S))
    np.testing.assert_allclose(nearest.mount("base_link", "odom", 5 * S), [2.0, 0.0, math.pi / 2], atol=1e-12)


def test_dynamic_readings_older_than_the_cache_are_forgotten() -> None:
    tree = FrameTree(cache_s=1.0)
    for k in range(5):
        tree.add(TF_TOPIC, planar_tf("odom", "base_link", float(k), 0.0, 0.0, stamp_ns=k * S))
    with pytest.raises(DataError, match="from 3.000 s to 4.000 s"):
        tree.transform("odom", "base_link", 2 * S)


@dataclass(frozen=True)
class Spec:
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]


def test_a_configured_mount_wins_over_a_drivers_default() -> None:
    tree = FrameTree.configured([Spec("base_link", "laser", (0.2, 0.0, 0.3), (0.0, 0.0, 0.1))], stamp_ns=7)
    tree.add(TF_STATIC_TOPIC, planar_tf("base_link", "laser", 0.0, 0.0, 0.0))  # the driver's zero mount
    tree.add(TF_STATIC_TOPIC, planar_tf("base_link", "camera", 0.25, 0.0, 0.0, z=0.45))  # nothing configures it
    np.testing.assert_allclose(tree.mount("laser"), [0.2, 0.0, 0.1], atol=1e-12)
    static = {t.child_frame_id: t for t in tree.static_message().transforms}
    assert set(static) == {"laser", "camera"}
    np.testing.assert_array_equal(static["laser"].translation, [0.2, 0.0, 0.3])
    assert static["laser"].stamp_ns == 7


def test_rpy_is_ros_fixed_axis_roll_then_pitch_then_yaw() -> None:
    roll, pitch, yaw = 0.3, -0.2, 1.1
    rx = np.array([[1, 0, 0], [0, math.cos(roll), -math.sin(roll)], [0, math.sin(roll), math.cos(roll)]])
    ry = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
    rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    np.testing.assert_allclose(rotation_matrix(quaternion_from_rpy(roll, pitch, yaw)), rz @ ry @ rx, atol=1e-12)


def test_a_static_mount_is_computed_once_and_again_when_a_static_edge_changes() -> None:
    tree = three_hops()
    first = tree.mount("tilted")
    assert np.array_equal(tree.mount("tilted"), first)
    tree.add(TF_STATIC_TOPIC, planar_tf("laser", "tilted", 0.3, 0.0, math.pi / 4))
    moved = tree.mount("tilted")
    assert not np.allclose(moved, first)
    assert np.allclose(moved, FrameTree.mount(three_hops_with_tilted_at(0.3), "tilted"))
    tree.add(TF_TOPIC, planar_tf("odom", "base_link", 1.0, 2.0, 0.5, stamp_ns=S))  # a dynamic edge elsewhere
    assert np.array_equal(tree.mount("tilted"), moved)
    returned = tree.transform("base_link", "tilted")
    returned[0, 3] = 99.0  # the caller's copy: the tree keeps its own
    assert tree.transform("base_link", "tilted")[0, 3] != 99.0


def three_hops_with_tilted_at(x: float) -> FrameTree:
    tree = FrameTree()
    tree.add(TF_STATIC_TOPIC, planar_tf("base_link", "mast", 1.0, 0.0, math.pi / 2))
    tree.add(TF_STATIC_TOPIC, planar_tf("mast", "laser", 0.5, 0.0, -math.pi / 2, z=0.2))
    tree.add(TF_STATIC_TOPIC, planar_tf("laser", "tilted", x, 0.0, math.pi / 4))
    return tree


def test_a_cycle_is_a_data_error() -> None:
    tree = FrameTree()
    tree.add(TF_STATIC_TOPIC, planar_tf("a", "b", 1.0, 0.0, 0.0))
    tree.add(TF_STATIC_TOPIC, planar_tf("b", "a", 1.0, 0.0, 0.0))
    with pytest.raises(DataError, match="cycle"):
        tree.transform("a", "b")


poses = st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.floats(-math.pi, math.pi))


@settings(max_examples=50, deadline=None)
@given(st.lists(poses, min_size=1, max_size=5), st.integers(0, 4), st.integers(0, 4))
def test_any_lookup_composes_with_its_inverse(chain, i, j) -> None:
    """A chain f0 -> f1 -> ... : the pose of fi in fj and of fj in fi multiply to the identity, and in
    the plane the pose of the last frame in f0 is the planar composition of the edges."""
    tree = FrameTree()
    for k, (x, y, yaw) in enumerate(chain):
        tree.add(TF_STATIC_TOPIC, planar_tf(f"f{k}", f"f{k + 1}", x, y, yaw))
    a, b = f"f{min(i, len(chain))}", f"f{min(j, len(chain))}"
    np.testing.assert_allclose(tree.transform(a, b) @ tree.transform(b, a), np.eye(4), atol=1e-9)
    x, y, yaw = 0.0, 0.0, 0.0
    for ex, ey, eyaw in chain:
        x, y, yaw = x + math.cos(yaw) * ex - math.sin(yaw) * ey, y + math.sin(yaw) * ex + math.cos(yaw) * ey, yaw + eyaw
    got = planar(tree.transform("f0", f"f{len(chain)}"))
    np.testing.assert_allclose(got[:2], [x, y], atol=1e-9)
    assert abs(math.remainder(got[2] - yaw, 2 * math.pi)) < 1e-9


REPO = Path(__file__).resolve().parents[1]
PACKAGE_ROOMS = ("logs", "drivers", "perception", "fusion", "tools")
# who may look inside a TFMessage: the tree itself, the CDR codecs (the typestore mapping and the direct
# encoder), and the logger's latch key (a split repeats each publisher's static transforms)
MAY_READ_TRANSFORMS = {"logs/frames.py", "logs/ros2.py", "logs/cdr.py", "logs/writer.py"}


def _code_strings(tree: ast.AST) -> set[str]:
    """The string constants of a module that are not docstrings."""
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
                  and node.body and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    return {node.value for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings}


def _reads_transforms(tree: ast.AST) -> bool:
    """Whether the module iterates over or indexes ``<something>.transforms`` (a TFMessage's content)."""
    def is_transforms(node: ast.AST) -> bool:
        return isinstance(node, ast.Attribute) and node.attr == "transforms"
    for node in ast.walk(tree):
        if isinstance(node, ast.For | ast.comprehension) and is_transforms(node.iter):
            return True
        if isinstance(node, ast.Subscript) and is_transforms(node.value):
            return True
        if isinstance(node, ast.Starred) and is_transforms(node.value):
            return True
    return False


def test_only_the_frames_module_reads_tf_and_only_the_topics_module_spells_its_names() -> None:
    """No module takes a TFMessage apart but the tree (so every /tf_static read goes through it), and no
    topic name of logs/topics.py is written out in code anywhere else. Syntactic: a module that copied
    the transforms into a list first would pass; the name rule catches how it found them."""
    names = {value for key, value in vars(topics).items() if key.endswith("_TOPIC")}
    assert {"/tf_static", "/tf", "/scan"} <= names
    spelled, readers = [], []
    for room in PACKAGE_ROOMS:
        for path in sorted((REPO / room).rglob("*.py")):
            name = path.relative_to(REPO).as_posix()
            tree = ast.parse(path.read_text(), name)
            if name != "logs/topics.py" and _code_strings(tree) & names:
                spelled.append(name)
            if name not in MAY_READ_TRANSFORMS and _reads_transforms(tree):
                readers.append(name)
    assert spelled == [], f"topic names spelt outside logs/topics.py: {spelled}"
    assert readers == [], f"TFMessage taken apart outside logs/frames.py: {readers}"
