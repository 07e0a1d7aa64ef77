"""Hypothesis strategies for every trundle message type (used by round-trip tests)."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from trundle.logs import messages as m

stamps = st.integers(min_value=0, max_value=(2**31 - 1) * 10**9)
names = st.text(st.characters(min_codepoint=32, max_codepoint=0x2FFF, exclude_categories=("Cs",)), max_size=12)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64, min_value=-1e12, max_value=1e12)
f32_any = st.floats(width=32)
small = st.integers(min_value=0, max_value=40)


def arrays(dtype, size, elements=None):
    return hnp.arrays(dtype, size, elements=elements)


def f64_matrix(shape):
    return hnp.arrays(np.float64, shape, elements=finite)


@st.composite
def laser_scans(draw):
    n = draw(small)
    return m.LaserScan(draw(stamps), draw(names), *(draw(st.floats(width=32, allow_nan=False)) for _ in range(7)),
                       draw(arrays(np.float32, n, f32_any)),
                       draw(arrays(np.float32, draw(st.sampled_from([0, n])), f32_any)))


@st.composite
def images(draw):
    h, w, c = draw(small), draw(small), draw(st.sampled_from([1, 3]))
    data = draw(arrays(np.uint8, h * w * c))
    return m.Image(draw(stamps), draw(names), h, w, "mono8" if c == 1 else "bgr8", w * c, data, draw(st.booleans()))


@st.composite
def camera_infos(draw):
    return m.CameraInfo(
        draw(stamps),
        draw(names),
        draw(st.integers(0, 4096)),
        draw(st.integers(0, 4096)),
        draw(st.sampled_from(["plumb_bob", "equidistant"])),
        draw(arrays(np.float64, draw(small), finite)),
        draw(f64_matrix((3, 3))),
        draw(f64_matrix((3, 3))),
        draw(f64_matrix((3, 4))),
        draw(st.integers(0, 8)),
        draw(st.integers(0, 8)),
    )


@st.composite
def joint_states(draw):
    n = draw(st.integers(0, 6))
    return m.JointState(
        draw(stamps),
        draw(names),
        tuple(draw(st.lists(names, min_size=n, max_size=n))),
        draw(arrays(np.float64, n, finite)),
        draw(arrays(np.float64, draw(st.sampled_from([0, n])), finite)),
        draw(arrays(np.float64, draw(st.sampled_from([0, n])), finite)),
    )


yaws = st.floats(min_value=-3.1, max_value=3.1)


@st.composite
def odometries(draw):
    return m.Odometry(draw(stamps), draw(names), draw(names), draw(finite), draw(finite), draw(yaws),
                      draw(finite), draw(finite), draw(finite), draw(f64_matrix((3, 3))), draw(f64_matrix((3, 3))))


@st.composite
def pose2ds(draw):
    return m.Pose2D(draw(stamps), draw(names), draw(finite), draw(finite), draw(yaws), draw(f64_matrix((3, 3))))


@st.composite
def transforms(draw):
    return m.TransformStamped(draw(stamps), draw(names), draw(names), draw(f64_matrix((3,))), draw(f64_matrix((4,))))


@st.composite
def grids(draw):
    h, w = draw(st.integers(1, 30)), draw(st.integers(1, 30))
    return m.OccupancyGrid(
        draw(stamps),
        draw(names),
        draw(st.floats(0.0625, 10.0, width=32)),
        draw(finite),
        draw(finite),
        0.0,
        draw(arrays(np.int8, (h, w), st.integers(-1, 100))),
    )


@st.composite
def paths(draw):
    n = draw(st.integers(0, 10))
    return m.Path(draw(stamps), draw(names), draw(arrays(np.int64, n, stamps)),
                  np.column_stack([draw(arrays(np.float64, n, finite)), draw(arrays(np.float64, n, finite)),
                                   draw(arrays(np.float64, n, yaws))]) if n else np.zeros((0, 3)))


statuses = st.builds(m.DiagnosticStatus, st.integers(0, 3), names, names, names,
                     st.lists(st.tuples(names, names), max_size=4).map(tuple))
colors = st.tuples(*(st.floats(0, 1, width=32),) * 4)


@st.composite
def image_markers(draw):
    n = draw(st.integers(0, 8))
    return m.ImageMarker(
        draw(stamps),
        draw(names),
        draw(names),
        draw(st.integers(-(2**31), 2**31 - 1)),
        draw(st.integers(0, 4)),
        (draw(finite), draw(finite)),
        draw(st.floats(0, 100, width=32)),
        draw(colors),
        draw(st.booleans()),
        draw(colors),
        draw(f64_matrix((n, 2))),
    )


@st.composite
def landmark_lists(draw):
    observations = [m.LandmarkObservation(draw(names), draw(finite), draw(finite), draw(f64_matrix((2, 2))),
                                          draw(st.none() | f64_matrix((3,))), draw(f64_matrix((4,))), draw(finite))
                    for _ in range(draw(st.integers(0, 4)))]
    return m.LandmarkList(draw(stamps), draw(names), tuple(observations))


@st.composite
def scene_markers(draw):
    markers = [m.SceneMarker(draw(stamps), draw(names), draw(names), draw(st.integers(-2**31, 2**31 - 1)),
                             draw(st.integers(0, 11)), draw(finite), draw(finite), draw(finite), draw(yaws),
                             draw(f64_matrix((3,))), draw(colors), draw(names))
               for _ in range(draw(st.integers(0, 4)))]
    return m.SceneMarkers(tuple(markers))


ALL_MESSAGES = {
    "LaserScan": laser_scans(),
    "CompressedImage": st.builds(
        m.CompressedImage, stamps, names, st.sampled_from(["jpeg", "png"]), st.binary(max_size=300)
    ),
    "Image": images(),
    "CameraInfo": camera_infos(),
    "JointState": joint_states(),
    "CanFrame": st.builds(
        m.CanFrame,
        stamps,
        names,
        st.integers(0, 2**29 - 1),
        st.binary(max_size=8),
        st.booleans(),
        st.booleans(),
        st.booleans(),
    ),
    "Odometry": odometries(),
    "Pose2D": pose2ds(),
    "TransformStamped": transforms(),
    "TFMessage": st.lists(transforms(), max_size=3).map(lambda t: m.TFMessage(tuple(t))),
    "OccupancyGrid": grids(),
    "Path": paths(),
    "DiagnosticArray": st.builds(m.DiagnosticArray, stamps, st.lists(statuses, max_size=3).map(tuple)),
    "ImageMarker": image_markers(),
    "LandmarkList": landmark_lists(),
    "SceneMarkers": scene_markers(),
}
