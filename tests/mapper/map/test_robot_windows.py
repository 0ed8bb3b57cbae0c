"""One keyframe window per robot (:class:`mapper.map.robot_windows.RobotWindows`): keyframe selection
and eviction per robot, the robot bound, callbacks for every robot's window, ``replace`` by robot,
and the single window's behaviour for one robot."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.map.robot_windows import RobotWindows, TooManyRobots, observed_box, robot_groups
from mapper.map.window import Keyframe, KeyframeWindow, WindowConfig

CONFIG = WindowConfig(max_keyframes=3, min_translation_m=0.1, min_rotation_deg=10.0, max_robots=2)


def kf(seq: int, x: float, robot: str = "", camera: str = "cam0") -> Keyframe:
    world_from_cam = np.eye(4)
    world_from_cam[0, 3] = x
    return Keyframe(seq=seq, stamp_ns=seq, camera=camera, K=np.array([100.0, 100.0, 80.0, 60.0]),
                    world_from_cam=world_from_cam, rgb=np.zeros((12, 16, 3), np.uint8), robot=robot)


def test_one_robot_is_the_single_window() -> None:
    windows, single = RobotWindows(CONFIG), KeyframeWindow(CONFIG)
    xs = [0.0, 0.05, 0.2, 0.25, 0.4, 0.6, 0.61, 0.9]
    got = [windows.consider(kf(i, x)).added for i, x in enumerate(xs)]
    want = [single.consider(kf(i, x)).added for i, x in enumerate(xs)]
    assert got == want
    assert [k.seq for k in windows.keyframes] == [k.seq for k in single.keyframes]
    assert windows.counts() == {"": len(single)} and len(windows) == len(single)


def test_selection_and_eviction_are_per_robot() -> None:
    windows = RobotWindows(CONFIG)
    alone = {"a": KeyframeWindow(CONFIG), "b": KeyframeWindow(CONFIG)}
    # interleaved: each robot moves 5 cm a frame, the two 12 m apart; with one window the jumps
    # between the robots would make every frame a keyframe
    for i in range(8):
        for frame in (kf(2 * i, 0.05 * i, "a"), kf(2 * i + 1, 12.0 + 0.05 * i, "b")):
            assert windows.consider(frame).added == alone[frame.robot].consider(frame).added, frame.seq
    a, b = windows.robot_keyframes("a"), windows.robot_keyframes("b")
    assert {k.robot for k in a} == {"a"} and {k.robot for k in b} == {"b"}
    assert a == alone["a"].keyframes and b == alone["b"].keyframes  # each as if it streamed alone
    assert len(a) == len(b) == 3 and len(windows) == 6 < 16
    assert windows.keyframes == a + b and windows.counts() == {"a": 3, "b": 3}


def test_callbacks_fire_for_every_robot_and_on_robot_before_its_first_keyframe() -> None:
    windows = RobotWindows(CONFIG)
    events: list[tuple[str, object]] = []
    windows.on_robot.append(lambda robot, window: events.append(("robot", robot)))
    windows.on_add.append(lambda k: events.append(("add", (k.robot, k.seq))))
    windows.on_evict.append(lambda k: events.append(("evict", (k.robot, k.seq))))
    windows.consider(kf(0, 0.0, "a"))
    windows.consider(kf(1, 12.0, "b"))
    for i in range(2, 5):
        windows.consider(kf(i, 0.3 * i, "a"))
    assert events == [("robot", "a"), ("add", ("a", 0)), ("robot", "b"), ("add", ("b", 1)),
                      ("add", ("a", 2)), ("add", ("a", 3)), ("add", ("a", 4)), ("evict", ("a", 0))]


def test_a_robot_beyond_the_bound_is_refused_and_changes_nothing() -> None:
    windows = RobotWindows(CONFIG)
    windows.consider(kf(0, 0.0, "a"))
    windows.consider(kf(1, 12.0, "b"))
    with pytest.raises(TooManyRobots, match="max_robots"):
        windows.consider(kf(2, 24.0, "c"))
    assert windows.robots == ("a", "b") and len(windows) == 2
    windows.consider(kf(3, 0.5, "a"))  # the known robots go on
    assert windows.counts() == {"a": 2, "b": 1}


def test_replace_puts_each_keyframe_in_its_robot_window() -> None:
    windows = RobotWindows(CONFIG)
    windows.consider(kf(0, 0.0, "a"))
    loaded = [kf(10 + i, 0.3 * i, "b") for i in range(5)] + [kf(20, 1.0, "a")]
    removed, added = windows.replace(loaded)
    assert [k.seq for k in removed] == [0]
    assert [k.seq for k in windows.robot_keyframes("b")] == [12, 13, 14]  # its newest max_keyframes
    assert [k.seq for k in windows.robot_keyframes("a")] == [20]
    assert {k.seq for k in added} == {12, 13, 14, 20}
    before = windows.keyframes
    with pytest.raises(TooManyRobots):
        windows.replace([kf(30, 0.0, "c")])
    assert windows.keyframes == before  # nothing changed


def test_swap_stays_in_the_robot_window() -> None:
    windows = RobotWindows(CONFIG)
    old = kf(0, 0.0, "b")
    windows.consider(kf(1, 12.0, "a"))
    windows.consider(old)
    new = kf(0, 0.0, "b")
    assert windows.swap(old, new)
    assert windows.robot_keyframes("b") == (new,) and len(windows.robot_keyframes("a")) == 1
    assert not windows.swap(old, new)  # no longer there


def depth_kf(seq: int, x: float, robot: str, depth_m: float | None = 2.0) -> Keyframe:
    """A keyframe at (x, 0, 0) looking along +z (identity rotation), with flat depth or none."""
    world_from_cam = np.eye(4)
    world_from_cam[0, 3] = x
    depth = None if depth_m is None else np.full((12, 16), depth_m, np.float32)
    return Keyframe(seq=seq, stamp_ns=seq, camera="cam0", K=np.array([8.0, 8.0, 8.0, 6.0]),
                    world_from_cam=world_from_cam, rgb=np.zeros((12, 16, 3), np.uint8), depth_m=depth,
                    robot=robot)


def test_observed_box_is_the_depth_or_the_frustum() -> None:
    lo, hi = observed_box(depth_kf(0, 5.0, "a"), max_range_m=8.0)
    assert lo[2] == pytest.approx(1.9) and hi[2] == pytest.approx(2.1)  # the depth, padded 10 cm
    assert lo[0] == pytest.approx(5.0 - 2.0 - 0.1, abs=0.3) and hi[0] <= 5.0 + 2.0 + 0.1
    lo, hi = observed_box(depth_kf(0, 5.0, "a", depth_m=None), max_range_m=8.0)
    assert lo[2] == pytest.approx(-0.1) and hi[2] == pytest.approx(8.1)  # camera centre to 8 m
    assert hi[0] - lo[0] == pytest.approx(16.0 + 0.2)  # the frustum's width at 8 m (fx 8, 16 px)


def test_robot_groups_ask_the_windows_that_observed_a_point() -> None:
    windows = [("a", [depth_kf(0, 0.0, "a")]), ("b", [depth_kf(1, 12.0, "b")])]
    xyz = np.array([[0.0, 0.0, 2.0], [12.0, 0.0, 2.0], [6.0, 0.0, 40.0], [11.0, 0.3, 2.0]], np.float32)
    groups = robot_groups(windows, xyz, max_range_m=8.0)
    assert groups is not None
    got = {robots: idx.tolist() for robots, idx in groups}
    assert got == {("a",): [0], ("b",): [1, 3], ("a", "b"): [2]}  # seen by none: every window
    # where both observed a point, both windows answer it
    both = [("a", [depth_kf(0, 0.0, "a")]), ("b", [depth_kf(1, 0.5, "b")])]
    assert robot_groups(both, xyz[:1], max_range_m=8.0) is None  # in every robot's boxes: as one window
    groups = robot_groups(both, np.array([[0.0, 0.0, 2.0], [0.6, 0.0, 2.0]], np.float32), max_range_m=8.0)
    assert groups is not None and {r: i.tolist() for r, i in groups} == {("a", "b"): [0], ("b",): [1]}


def test_robot_groups_with_one_robot_are_none() -> None:
    xyz = np.zeros((3, 3), np.float32)
    assert robot_groups([("a", [depth_kf(0, 0.0, "a")])], xyz, 8.0) is None
    assert robot_groups([("a", [depth_kf(0, 0.0, "a")]), ("b", [])], xyz, 8.0) is None
