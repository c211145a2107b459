"""``olsplat aggregate --cluster``: the offline aggregation of several flights on a Ray cluster,
the map sharded by ground tile (``storage/tiles.py``).

- One Ray task per view: its regions and features (the scene's encoding cache, else computed),
  its Top-K render and observations, split by tile, each part sent to its tile.
- One actor per tile: a ``TileShard`` (the same class the single machine uses), holding that
  tile's store on disk; at the end it refines its map, and the driver gathers the union.

Fault tolerance comes from Ray, and from the store being on disk: a tile actor that dies is
restarted (``max_restarts``) and opens its shard again, so it knows the views it holds; the
calls in flight are retried (``max_task_retries``), a view task whose worker died is run again
(``max_retries``), and a shard records a view's part once, by name: the map holds every view
once, the same map as an uninterrupted run. Every node of the cluster must have olsplat
installed and see the scene folders and the output folder at the same paths (one computer, or
a shared file system).

Ray is an optional extra (``pip install olsplat[cluster]``): nothing else imports this module.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import OlsplatInputError
from ..memory import peak_rss_mb
from ..method import Method, view_observations
from ..pipeline.offline import flight_view_name, same_prior_map
from ..pipeline.scene_folder import Scene, view_features
from ..scene import Camera, Gaussians, read_ply
from ..storage import LanguageMap
from ..storage.tiles import TileGrid, TileShard, Tiling, check_manifest, shard_folder, split_view, union_of

# each view task takes one core; its kernels must not spread over the others' cores
_ONE_THREAD = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def connect(address: str, num_cpus: int | None = None) -> list[str]:
    """Join the Ray cluster at ``address`` ("auto": the one ``ray start`` runs on this computer,
    else a local one started now, on 127.0.0.1 only, with ``num_cpus`` worker slots (None: one
    per core); "ray://HOST:PORT": a Ray client connection); the addresses of its nodes. An
    address that does not answer is one OlsplatInputError. Usage statistics are never sent."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    # Ray's own switch for a computer that is not part of a network cluster: its servers then
    # listen on the loopback address only (read when Ray is first imported)
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    import ray

    runtime_env = {"env_vars": _ONE_THREAD}
    try:
        if address == "auto":
            try:
                ray.init(address="auto", runtime_env=runtime_env, log_to_driver=False)
            except ConnectionError:  # no cluster on this computer: a local one, for this run
                ray.init(
                    address="local",
                    num_cpus=num_cpus,
                    include_dashboard=False,
                    runtime_env=runtime_env,
                    log_to_driver=False,
                )
        else:
            ray.init(address=address, runtime_env=runtime_env, log_to_driver=False)
    except (ConnectionError, ValueError, RuntimeError) as exc:
        raise OlsplatInputError(f"--cluster {address}: cannot join the Ray cluster: {exc}") from exc
    return node_addresses()


def node_addresses() -> list[str]:
    """The addresses of the joined cluster's live nodes."""
    import ray

    return sorted({node["NodeManagerAddress"] for node in ray.nodes() if node["Alive"]})


def leave() -> None:
    """Leave the cluster joined by ``connect`` (a local one started there stops)."""
    import ray

    ray.shutdown()


@lru_cache(maxsize=2)
def _scene(folder: str) -> Scene:
    return Scene.open(folder)


@lru_cache(maxsize=1)
def _map(ply: str, tile_m: float) -> tuple[Gaussians, Tiling]:
    """A worker's prior map and tiling, made once per worker process (memory-mapped map)."""
    gaussians = read_ply(ply)
    return gaussians, Tiling.of(gaussians.means, TileGrid(tile_m))


@lru_cache(maxsize=2)
def _encoder(spec: str, weights: str | None):
    from ..encoders.spec import encoder_from_spec

    return encoder_from_spec(spec, weights)


def observe_and_record(
    folder: str, camera: Camera, name: str, tile_m: float, method: Method, encoder: tuple[str, str | None], shards: list
) -> tuple[int, float]:
    """One view (``camera`` of the scene at ``folder``) observed and its parts recorded in their
    tiles under ``name``; (the number of tiles that took it now, fewer for a retried view; this
    worker process's peak resident set in MB)."""
    import ray

    scene = _scene(folder)
    gaussians, tiling = _map(str(scene.ply), tile_m)
    label_maps, bank = view_features(scene, camera, _encoder(*encoder))
    observations, stacked, _ = view_observations(gaussians, camera, label_maps, bank, method)
    parts = split_view(tiling, observations, stacked)
    added = sum(ray.get([shards[t].record.remote(name, part, rows) for t, (part, rows) in parts.items()]))
    return added, peak_rss_mb()


class RayTileShard(TileShard):
    """A tile's shard as a Ray actor: ``where`` tells which process holds it (the tests kill it)."""

    def where(self) -> tuple[int, str]:
        """(the actor's process id, its shard folder)."""
        return os.getpid(), str(self.store.folder)

    def peak_rss_mb(self) -> float:
        """This actor process's peak resident set (MB)."""
        return peak_rss_mb()


def aggregate_on_ray(
    scenes: list[Scene],
    method: Method,
    encoder: tuple[str, str | None],
    out: Path,
    tile_m: float,
    address: str = "auto",
    codebook: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    on_start: Callable[[list], None] | None = None,
) -> dict:
    """Aggregate every view of ``scenes`` (flights over one prior map) into ``out``: the tiles'
    stores under ``out/store`` and the union map ``out/language_map.npz`` (codebook form with
    ``codebook`` centres). The cluster is joined at ``address`` and left at the end, unless the
    caller has joined one already (then that one is used, and kept). ``encoder`` is (spec,
    weights) as the CLI takes them; each worker makes its own. ``progress(done, total)`` after
    each view; ``on_start(actors)`` once the tile actors exist (the tests use it to kill one).
    Returns figures, as ``aggregate_flights``, with each tile actor's peak resident set, the
    highest of the view tasks' worker processes, and the cluster's node addresses."""
    import ray

    gaussians = same_prior_map(scenes)
    tiling = Tiling.of(gaussians.means, TileGrid(tile_m))
    check_manifest(out / "store", tiling, write=True)
    owned = not ray.is_initialized()  # a caller that joined a cluster itself keeps it after the run
    nodes = connect(address) if owned else node_addresses()
    start = time.perf_counter()
    try:
        shard = ray.remote(max_restarts=-1, max_task_retries=-1, num_cpus=0)(RayTileShard)
        actors: list[Any] = [  # Ray's actor handles (untyped)
            shard.remote(str(shard_folder(out / "store", tiling, t)), len(members))
            for t, members in enumerate(tiling.members)
        ]
        if sum(ray.get([actor.__len__.remote() for actor in actors])):
            raise OlsplatInputError(f"{out / 'store'} already holds views: choose a new --out")
        if on_start is not None:
            on_start(actors)
        task = ray.remote(max_retries=5, num_cpus=1)(observe_and_record)
        pending = [
            task.remote(
                str(scene.folder), camera, flight_view_name(f, len(scenes), camera), tile_m, method, encoder, actors
            )
            for f, scene in enumerate(scenes)
            for camera in scene.cameras
        ]
        total, worker_peak = len(pending), 0.0
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            try:
                _added, peak = ray.get(done[0])
            except ray.exceptions.RayTaskError as exc:  # bad input in a view (a missing photo...): its one error
                if isinstance(exc.cause, OlsplatInputError):
                    raise exc.cause from None
                raise
            worker_peak = max(worker_peak, peak)
            if progress is not None:
                progress(total - len(pending), total)
        name = _encoder(*encoder).name if len(tiling) > 1 else None  # each tile's own map too (one tile: the union)
        features, observed = union_of(
            tiling, ray.get([actor.refine.remote(method.aggregation, name) for actor in actors])
        )
        peaks = ray.get([actor.peak_rss_mb.remote() for actor in actors])
    finally:
        if owned:
            ray.shutdown()
    if features is None:
        raise OlsplatInputError(f"{', '.join(str(s.folder) for s in scenes)}: no view observed any Gaussian")
    LanguageMap(features, observed, _encoder(*encoder).name).save(out / "language_map.npz", codebook)
    seconds = time.perf_counter() - start
    return {
        "seconds": seconds,
        "views_per_second": total / seconds,
        "peak_rss_mb": peak_rss_mb(),
        "actor_peak_rss_mb": peaks,
        "worker_peak_rss_mb": worker_peak,
        "observed_gaussians": int(np.count_nonzero(observed)),
        "tiles": len(tiling),
        "nodes": nodes,
    }
