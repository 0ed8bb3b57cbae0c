"""The ingest path: one decoded ``frame`` -> the keyframe window, the integrator, an ``ack``.

:func:`ingest_frame` runs on the ingest thread. Under the state lock it validates the frame against
the map (OV space and feature dimension), then recognises a resent frame (same seq, stamp, camera,
pose and K as a keyframe already in the window: acked ``accepted`` as a duplicate, not added twice),
then lets the frame's robot's window (:class:`mapper.map.robot_windows.RobotWindows`; a robot beyond
``window.max_robots`` is ``bad_request``) decide keyframe or not. A resent frame
counts as a duplicate only after it passed the same validation as a new one. Outside the lock the
new keyframe goes to the integrator (:mod:`mapper.node.integration`).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from mapper.map.window import Keyframe, fit_image, fit_intrinsics, fit_ov
from mapper.node.context import NodeContext
from mapper.node.integration import IntegrateJob
from protocol.errors import ProtocolError
from protocol.messages import Ack, AckStatus, Frame

__all__ = ["ingest_frame"]

log = logging.getLogger("mapper.node.service")


def _reject(ctx: NodeContext, frame: Frame, reason: str) -> Ack:
    """A rejected ack (called with the state lock held)."""
    ctx.state.ack_counts["rejected"] += 1
    ctx.warn_limited("ingest:rejected", "frame seq %d rejected: %s", frame.seq, reason)
    return Ack(seq=frame.seq, status="rejected", map_version=ctx.state.map_version, reason=reason,
               id=frame.id)


def _check_against_map(ctx: NodeContext, frame: Frame) -> Ack | None:
    """The frame's OV features against the map's (state lock held): raises ``ov_space_mismatch``,
    returns a rejected ack for another feature dimension, None when the frame fits."""
    state = ctx.state
    if frame.ov is None:
        return None
    if state.ov_space is not None and frame.ov_space != state.ov_space:
        raise ProtocolError(
            "ov_space_mismatch",
            f"frame seq {frame.seq}: ov_space {frame.ov_space!r} differs from the map's "
            f"{state.ov_space!r}; send features of that space, or load/start a map for yours",
        )
    dim = int(frame.ov.shape[2])
    if state.ov_dim is not None and dim != state.ov_dim:
        return _reject(
            ctx, frame,
            f"ov feature dimension {dim} differs from the map's {state.ov_dim} for space {state.ov_space!r}",
        )
    return None


def _check_robot(ctx: NodeContext, frame: Frame) -> None:
    """Raise ``bad_request`` when the frame names a robot beyond ``window.max_robots`` (state lock
    held; nothing changed)."""
    from mapper.map.robot_windows import TooManyRobots

    try:
        ctx.state.window.check_robot(frame.robot)
    except TooManyRobots as exc:
        raise ProtocolError("bad_request", f"frame seq {frame.seq}: {exc}") from None


def _duplicate(ctx: NodeContext, frame: Frame, kept_K: np.ndarray) -> Ack | None:
    """An ``accepted`` ack when ``frame`` is already a keyframe of its robot's window (a client's
    retry after a timeout or a node restart: same seq, stamp, camera, pose and K), else None (state
    lock held)."""
    state = ctx.state
    for kept in state.window.robot_keyframes(frame.robot):
        same_id = (kept.seq, kept.stamp_ns, kept.camera) == (frame.seq, frame.stamp_ns, frame.camera)
        same_pose = np.array_equal(kept.world_from_cam, frame.world_from_cam)
        if same_id and same_pose and np.array_equal(kept.K, kept_K):
            state.ack_counts["accepted"] += 1
            ctx.frames_duplicate += 1
            return Ack(seq=frame.seq, status="accepted", map_version=state.map_version, id=frame.id,
                       reason=f"duplicate: frame seq {frame.seq} is already a keyframe of the map")
    return None


def _changed_region(ctx: NodeContext, keyframe: Keyframe) -> tuple[np.ndarray, np.ndarray] | None:
    """The box ``map_updated`` names for a new keyframe (:func:`mapper.map.carving.changed_region`:
    its depth points, about 4 000 of them, or its frustum; the camera too where carving clears)."""
    from mapper.map.carving import changed_region

    gcfg = ctx.config.global_map
    height, width = keyframe.rgb.shape[:2]
    stride = max(2, int(np.ceil(np.sqrt(width * height / 4096.0))))
    try:
        return changed_region(keyframe.K, keyframe.world_from_cam, width, height, keyframe.depth_m,
                              gcfg.min_depth_m, gcfg.max_depth_m, include_camera=gcfg.carve, stride=stride)
    except (ValueError, FloatingPointError):  # never refuse a frame over its notice
        return None


def ingest_frame(ctx: NodeContext, frame: Frame) -> Ack:
    """Consider one validated frame for the window; returns its ack (raises ``ProtocolError`` for an
    error reply: nothing changed)."""
    keyframe = Keyframe(
        seq=frame.seq,
        stamp_ns=frame.stamp_ns,
        camera=frame.camera,
        K=frame.K,
        world_from_cam=frame.world_from_cam,
        rgb=frame.rgb,
        depth_m=frame.depth_m,
        ov=frame.ov,
        ov_space=frame.ov_space,
        robot=frame.robot,
    )
    state = ctx.state
    if ctx.config.follow_map:  # a read-only copy of another node's map
        with state.lock:
            return _reject(ctx, frame, f"this node serves a read-only copy of map {ctx.config.follow_map!r} "
                                       "(follow_map): send frames to the node that writes it")
    max_side = ctx.config.window.max_image_side
    kept_K = fit_intrinsics(frame.K, frame.width, frame.height, max_side)  # K as a keyframe keeps it
    max_cells = ctx.config.window.max_ov_cells
    big_image = 0 < max_side < max(frame.width, frame.height)
    big_ov = frame.ov is not None and 0 < max_cells < frame.ov.shape[0] * frame.ov.shape[1]
    events = bool(ctx.config.events_endpoint)
    will_keep = False
    if big_image or big_ov or events:
        with state.lock:  # work only for what will be a keyframe (the ingest thread alone adds)
            _check_robot(ctx, frame)
            will_keep = state.window.is_keyframe(frame.camera, frame.world_from_cam, frame.robot)[0]
    if will_keep and (big_image or big_ov):  # outside the lock (tens of ms at 4096 px)
        fitted = fit_ov(fit_image(keyframe, max_side) if big_image else keyframe, max_cells)
        if fitted is not keyframe:
            keyframe = fitted
            ctx.frames_downscaled += 1
    region = _changed_region(ctx, keyframe) if events and will_keep else None
    with state.lock:
        _check_robot(ctx, frame)
        refused = _check_against_map(ctx, frame)
        if refused is not None:
            return refused
        duplicate = _duplicate(ctx, frame, kept_K)
        if duplicate is not None:
            return duplicate
        update = state.window.consider(keyframe)
        status: AckStatus
        if update.added:
            if frame.ov is not None:
                state.ov_space = frame.ov_space
                state.ov_dim = int(frame.ov.shape[2])
            state.map_version += 1
            state.keyframes_evicted += len(update.evicted)
            if ctx.evicted_views is not None:
                for old in update.evicted:
                    ctx.evicted_views.put(old, state.global_map)
            status = "keyframe"
            ctx.publish(state.map_version, len(state.window), region)
        else:
            status = "accepted"
        state.ack_counts[status] += 1
        version = state.map_version
        job = None
        if update.added:
            ctx.integration.submitted += 1  # with the window add: save's drain target
            job = IntegrateJob(state.global_map, keyframe, version, state.ov_space, time.monotonic())
    if job is not None:
        # outside the state lock: the integrator thread fuses it into the global map shortly after
        # this ack (queries keep working on their snapshot meanwhile); inline when
        # ``global_map.integrate_queue`` is 0 or the integrator is not running
        ctx.integration.submit(job)
    log.debug(
        "frame seq %d (%s): %s, moved %.3f m, turned %.1f deg",
        frame.seq,
        frame.camera,
        status,
        update.translation_m,
        update.rotation_deg,
    )
    return Ack(seq=frame.seq, status=status, map_version=version, id=frame.id)
