"""``save`` and ``load``: the map to and from a ``.govmap`` file in the node's map directory
(:class:`mapper.node.store.MapStore`), and the autosave (at start, periodic, final)."""

from __future__ import annotations

import logging
import os
import time

from mapper.map.global_map import GlobalSemanticMap
from mapper.map.robot_windows import TooManyRobots
from mapper.map.window import keyframes_from_arrays, keyframes_to_arrays
from mapper.node.config import to_dict
from mapper.node.context import NodeContext
from mapper.node.store import StoreError, StoreWriteError
from protocol.errors import ProtocolError
from protocol.messages import Load, Message, Ok, Save

__all__ = ["Persistence"]

log = logging.getLogger("mapper.node.service")


class Persistence:
    """Saving and loading the node's map (``save`` / ``load`` requests and the autosave)."""

    def __init__(self, ctx: NodeContext) -> None:
        self.ctx = ctx
        self._last_autosave = time.monotonic()

    # -- requests -----------------------------------------------------------------------------

    def _refuse_when_following(self, what: str) -> None:
        """A follower (``follow_map``) neither saves nor loads on request: its map is the writer's."""
        name = self.ctx.config.follow_map
        if name:
            raise ProtocolError("bad_request", f"{what} refused: this node serves a read-only copy of map "
                                               f"{name!r} (follow_map); {what} on the node that writes it")

    def handle_save(self, msg: Message) -> Ok:
        assert isinstance(msg, Save)
        self._refuse_when_following("save")
        try:
            path, version, count = self.save_to(msg.name, reason="request")
        except StoreWriteError as exc:
            log.error("save of map %r failed: %s", msg.name, exc)
            raise ProtocolError("internal", f"save failed on the node: {exc}") from None
        except StoreError as exc:
            raise ProtocolError("bad_request", f"save failed: {exc}") from None
        return Ok(id=msg.id, message=f"saved map version {version} ({count} keyframes) to {path}")

    def handle_load(self, msg: Message) -> Ok:
        assert isinstance(msg, Load)
        self._refuse_when_following("load")
        return Ok(id=msg.id, message=self.load_map(msg.name))

    # -- saving -------------------------------------------------------------------------------

    def save_to(self, name: str, reason: str) -> tuple[str, int, int]:
        """Snapshot under the lock, write outside it. Returns (path, map_version, keyframes).
        Every keyframe acked before the save (at least those in the saved window) is integrated
        into the saved global map first (the integrator's backlog is drained)."""
        ctx = self.ctx
        with ctx.state.lock:
            snap = ctx.state.snapshot()
            target = ctx.integration.submitted
            global_map = ctx.state.global_map
        ctx.integration.wait_integrated(target)
        if ctx.evicted_views is not None:
            ctx.evicted_views.process_pending()  # the views of keyframes that left, in the saved map
        # the map as of now: every keyframe of ``snap`` and perhaps a few acked since (its own lock)
        global_arrays, global_manifest = global_map.to_arrays()
        arrays, entries = keyframes_to_arrays(snap.keyframes)
        arrays.update(global_arrays)
        manifest = {
            "map_version": snap.map_version,
            "ov_space": snap.ov_space,
            "ov_dim": snap.ov_dim,
            "keyframes": entries,
            "global_map": global_manifest,
            "saved_unix_s": time.time(),
            "config": to_dict(ctx.config),
        }
        started = time.monotonic()
        path = ctx.store.save(name, arrays, manifest)
        elapsed = time.monotonic() - started
        with ctx.state.lock:
            ctx.state.last_save = {"name": name, "map_version": snap.map_version, "unix_s": time.time()}
        ctx.saved_version = snap.map_version
        log.info("%s save: map version %d (%d keyframes) -> %s in %.2f s", reason, snap.map_version,
                 len(snap.keyframes), path, elapsed)
        return str(path), snap.map_version, len(snap.keyframes)

    def maybe_autosave(self) -> None:
        """The periodic save (``autosave_name`` every ``autosave_interval_s``) of a changed map."""
        cfg = self.ctx.config
        if not cfg.autosave_name or cfg.autosave_interval_s <= 0:
            return
        if time.monotonic() - self._last_autosave < cfg.autosave_interval_s:
            return
        self._last_autosave = time.monotonic()
        with self.ctx.state.lock:
            version = self.ctx.state.map_version
        if version == self.ctx.saved_version:
            return
        try:
            self.save_to(cfg.autosave_name, reason="periodic")
        except StoreError as exc:
            log.error("periodic save failed: %s", exc)

    # -- loading ------------------------------------------------------------------------------

    def load_autosave(self) -> bool:
        """Load ``autosave_name`` from the map directory if configured and present. A file that
        cannot be loaded is renamed to ``NAME.govmap.unreadable`` (kept for inspection, not
        overwritten by the next autosave) and the node starts empty. Returns True if loaded."""
        ctx = self.ctx
        cfg = ctx.config
        if not (cfg.load_autosave_on_start and cfg.autosave_name):
            return False
        try:
            path = ctx.store.path_for(cfg.autosave_name)
        except StoreError as exc:
            log.error("autosave %r: %s", cfg.autosave_name, exc)
            return False
        if not path.is_file():
            log.info("no autosave at %s: starting with an empty map", path)
            return False
        try:
            message = self.load_map(cfg.autosave_name)
        except ProtocolError as exc:
            aside = path.with_name(path.name + ".unreadable")
            log.error("cannot load the autosave %s (%s); moved it to %s and starting empty", path,
                      exc.message, aside)
            try:
                os.replace(path, aside)
            except OSError as move_exc:
                log.error("could not move %s aside: %s", path, move_exc)
            return False
        log.info("start-up: %s", message)
        with ctx.state.lock:
            ctx.saved_version = ctx.state.map_version
        return True

    def load_map(self, name: str) -> str:
        """Replace the window and the global map with the saved map ``name``; returns a note.
        Raises ``ProtocolError`` (nothing changed) when the file is missing or damaged. Maps
        saved without a global map section get one rebuilt from their keyframes."""
        ctx = self.ctx
        try:
            arrays, manifest = ctx.store.load(name)
            keyframes = keyframes_from_arrays(arrays, manifest.get("keyframes"))
        except (StoreError, ValueError) as exc:
            raise ProtocolError("bad_request", f"load failed: {exc}") from None
        ov_space = manifest.get("ov_space")
        ov_dim = manifest.get("ov_dim")
        saved_version = manifest.get("map_version")
        valid_space = ov_space is None or isinstance(ov_space, str)
        if not valid_space or not (ov_dim is None or isinstance(ov_dim, int)):
            raise ProtocolError("bad_request", f"load failed: map {name!r} has a corrupt manifest (ov)")
        if ctx.config.ov_space is not None and ov_space is not None and ov_space != ctx.config.ov_space:
            raise ProtocolError(
                "ov_space_mismatch",
                f"map {name!r} holds ov_space {ov_space!r}; this node is pinned to {ctx.config.ov_space!r}",
            )
        # build the new global map aside, so a damaged section changes nothing
        fresh = GlobalSemanticMap(ctx.config.global_map, fusion=ctx.state.global_map.fusion,
                                  tile_dir=ctx.state.global_map.tile_dir)
        section = manifest.get("global_map")
        try:
            if section is not None:
                fresh.restore(arrays, section, map_version=0)
            else:
                for keyframe in keyframes:
                    fresh.integrate(keyframe)
        except ValueError as exc:
            raise ProtocolError("bad_request", f"load failed: map {name!r}: {exc}") from None
        state = ctx.state
        with state.lock:
            try:
                state.window.replace(keyframes)  # checks the robots first: nothing changed on refusal
            except TooManyRobots as exc:
                raise ProtocolError("bad_request", f"load failed: map {name!r}: {exc}") from None
            state.ov_space = ov_space if ov_space is not None else ctx.config.ov_space
            state.ov_dim = ov_dim
            # keep the saved version when it is ahead, so versions seen by clients stay comparable
            if isinstance(saved_version, int) and saved_version > state.map_version:
                state.map_version = saved_version
            else:
                state.map_version += 1
            version, loaded = state.map_version, state.window.keyframes
            count = len(loaded)
            fresh.retag(version)
            state.global_map = fresh  # a frame being integrated into the old map right now is dropped
            ctx.publish(version, count)
        # The loaded map is ready to query when the reply goes out: its snapshot and normalised
        # features (what the first query_points would compute) are made here, off the query path.
        fresh.snapshot().unit_feature_blocks()
        for listener in ctx.load_listeners:
            listener(fresh, version, loaded)
        points = len(state.global_map)
        log.info("loaded map %r: %d keyframes, %d global points, now map version %d", name, count, points,
                 version)
        return f"loaded map {name!r}: {count} keyframes, {points} map points, map version {version}"
