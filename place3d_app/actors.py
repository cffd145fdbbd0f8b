"""Population scoring on long-lived Ray actors: one per GPU, optionally plus CPU actors.

A Ray *task* (``distributed.RayExecutor.map``) starts from a bare worker each time: it imports the
backend, loads the P-SOG from the on-disk cache and compiles its kernels on every call. A ``ScoringPool``
keeps that state in actors instead, so that from the second CMA-ES generation on a chunk of rigs costs
only its ``msog_batch`` launch:

    >>> import ray
    >>> from place3d_app.actors import ScoringPool
    >>> pool = ScoringPool(ray, gpu_actors=2, cpu_actors=1)            # on a 2-GPU host
    >>> scores = pool.score(psog_spec, "place3d_16ch", poses, chunk=8)   # (P,), candidate order

- Each actor holds one backend instance and the P-SOGs it was asked for (memoised by ``PSOGSpec``).
  A GPU actor reserves ``num_gpus=1``; Ray then sets ``CUDA_VISIBLE_DEVICES`` to that GPU, so its
  backend sees it as device 0 (``warp:cuda:0``, ``opencl:nvidia``).
- Backends: a GPU actor runs the run's backend when that is a GPU one, else the first GPU backend it
  finds; a CPU actor runs ``cpu_backends`` (one name, or one per actor), else the run's backend when that
  is a CPU one, else the first of opencl:pocl, warp:cpu, reference it finds. The backends agree bit for
  bit, so a mixed pool returns the scores of one backend in-process (``tests/test_actors.py``).
- Dispatch is dynamic: the batch is cut into chunks, and an idle actor takes the next one, so a fast
  actor takes more chunks than a slow one. From the measured rate of each actor (rigs per second,
  kept across calls) an actor is left idle for a chunk it would finish after the faster actors could
  have finished all that is left, counting what they are still scoring; results are placed by chunk index, so the order never depends on
  timing.
- An exception in an actor reaches the caller as ``ActorScoringError`` naming the actor, its backend
  and the candidates of the chunk. An actor process that dies is restarted and its chunk retried
  (``max_restarts`` / ``max_task_retries``), as the task path retries a dead worker.
"""

from __future__ import annotations

import os
import socket
import time
from typing import Sequence

import numpy as np

__all__ = ["ScoringPool", "ScoringActor", "ActorScoringError", "is_gpu_backend", "worth_dispatching", "CPU_BACKENDS",
           "GPU_BACKENDS"]

#: Backends a CPU actor picks from when none is named, fastest first (docs/performance.md).
CPU_BACKENDS = ("opencl:pocl", "warp:cpu", "reference")
#: Backends a GPU actor picks from when the run's backend is not a GPU one.
GPU_BACKENDS = ("warp:cuda:0", "opencl:nvidia")


class ActorScoringError(RuntimeError):
    """An actor failed to score a chunk; the message names the actor, its backend and the candidates."""


def is_gpu_backend(name: str) -> bool:
    """True for a backend name that needs a GPU (``warp:cuda:N``, an OpenCL platform other than PoCL).

    Args:
        name: a backend name such as ``warp:cuda:0``, ``opencl:nvidia``, ``opencl:pocl``, ``warp:cpu``.
    """
    name = str(name).lower()
    return name.startswith("warp:cuda") or (name.startswith("opencl:") and name != "opencl:pocl")


def _first_available(candidates: Sequence[str]) -> str:
    from place3d_kernels.backends.registry import available_backends

    have = available_backends()
    for name in candidates:
        if name in have:
            return name
    raise RuntimeError(f"none of {list(candidates)} is available in this actor (available: {have}); name a "
                       f"backend the actor's host has")


def worth_dispatching(n: int, rate: float | None, other_rates: Sequence[float | None], left: int) -> bool:
    """Whether an idle actor should take a chunk of ``n`` rigs while ``left`` rigs (this chunk included,
    and those the busy actors still hold) remain: not when the other actors, at their measured rates
    (rigs/s), would clear all of them before this one finished its chunk. Unknown rates (an actor's first
    chunk) always dispatch. Counting the rigs in flight matters: two equal GPUs with one chunk each left
    would otherwise leave the one measured a little slower idle for good (seen on a 2 x H200 host).

    Args:
        n: rigs in the chunk; rate: this actor's rate; other_rates: the others'; left: rigs queued or in
            flight on the other actors.
    """
    if rate is None or not other_rates or any(r is None for r in other_rates):
        return True
    return n / rate <= left / sum(other_rates)


class ScoringActor:
    """The state of one actor: a backend and its P-SOGs. ``ScoringPool`` runs it as a Ray actor.

    Args:
        backend: a backend name, or ``"gpu"`` / ``"cpu"`` for the first available of ``GPU_BACKENDS`` /
            ``CPU_BACKENDS`` on the actor's host.
    """

    def __init__(self, backend: str) -> None:
        from place3d_kernels.backends.registry import get_backend

        name = {"gpu": GPU_BACKENDS, "cpu": CPU_BACKENDS}.get(backend)
        self.backend = get_backend(_first_available(name) if name else backend)
        self._psogs: dict = {}

    def info(self) -> dict:
        """Where the actor runs: backend name, host, pid and the GPU Ray gave it."""
        return {"backend": self.backend.name, "host": socket.gethostname(), "pid": os.getpid(),
                "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES")}

    def psog(self, spec):
        """The P-SOG of ``spec``, loaded once (from the cache the driver filled; built on a miss)."""
        if spec not in self._psogs:
            import dataclasses

            # the cache key holds no backend, so this actor's backend reads the driver's cache entry
            self._psogs[spec] = dataclasses.replace(spec, backend=self.backend.name).load()
        return self._psogs[spec]

    def score(self, spec, lidar, poses, occlusion: str = "sog", task: str = "seg",
              normalisation: str = "paper") -> tuple:
        """``(scores, seconds)``: ``msog_batch`` of the chunk ``poses`` (n, L, 6) and its time here."""
        from place3d_kernels.metrics import msog_batch
        from place3d_kernels.spec import resolve_lidar

        psog = self.psog(spec)
        t = time.perf_counter()
        s = msog_batch(psog, resolve_lidar(lidar), poses, occlusion=occlusion, task=task, backend=self.backend,
                       normalisation=normalisation)
        return np.asarray(s, dtype=np.float64), time.perf_counter() - t


class ScoringPool:
    """Ray actors that score chunks of rigs with warm state (see the module docstring).

    Args:
        ray: the imported ``ray`` module, initialised.
        gpu_actors: actors reserving one GPU each (the cluster must have that many GPUs).
        cpu_actors: actors on CPU cores.
        backend: the run's backend name (decides the actors' backends, see the module docstring).
        cpu_backends: CPU actors' backend: one name, or one per actor (cycled).
        gpu_backend: GPU actors' backend (default: the run's when it is a GPU one, else ``"gpu"``).
        cpus_per_actor: CPUs each actor reserves.
        max_restarts: restarts of an actor whose process dies (its chunk is retried).
    """

    def __init__(self, ray, gpu_actors: int = 0, cpu_actors: int = 0, backend: str | None = None,
                 cpu_backends: str | Sequence[str] | None = None, gpu_backend: str | None = None,
                 cpus_per_actor: float = 1, max_restarts: int = 2) -> None:
        gpu_actors, cpu_actors = int(gpu_actors), int(cpu_actors)
        if gpu_actors < 0 or cpu_actors < 0 or gpu_actors + cpu_actors == 0:
            raise ValueError(f"a scoring pool needs at least one actor, got gpu_actors={gpu_actors}, "
                             f"cpu_actors={cpu_actors}; use --gpu-actors N and/or --cpu-actors N")
        have = ray.cluster_resources().get("GPU", 0)
        if gpu_actors > have:
            # Ray would leave the actors pending for ever: refuse before any work
            raise ValueError(f"gpu_actors={gpu_actors} but the Ray cluster has {have:g} GPU(s); use "
                             f"--gpu-actors {int(have)} or join a cluster with more GPUs (--ray-address)")
        cpus = ray.cluster_resources().get("CPU", 0)
        if (gpu_actors + cpu_actors) * cpus_per_actor > cpus:
            raise ValueError(f"{gpu_actors + cpu_actors} actors of {cpus_per_actor:g} CPU each need more than the "
                             f"{cpus:g} CPU(s) of the Ray cluster; use fewer actors, or start the cluster with "
                             f"more logical CPUs (--num-cpus, ray.init(num_cpus=...))")
        self._ray = ray
        if gpu_backend is None:
            gpu_backend = backend if backend and is_gpu_backend(backend) else "gpu"
        if cpu_backends is None:
            cpu_backends = backend if backend and not is_gpu_backend(backend) and backend != "auto" else "cpu"
        cpu_list = [cpu_backends] if isinstance(cpu_backends, str) else list(cpu_backends)
        remote = ray.remote(ScoringActor)
        opts = dict(num_cpus=cpus_per_actor, max_restarts=max_restarts, max_task_retries=max_restarts)
        self.kinds = ["gpu"] * gpu_actors + ["cpu"] * cpu_actors
        self.requested = [gpu_backend] * gpu_actors + [cpu_list[i % len(cpu_list)] for i in range(cpu_actors)]
        self.actors = [remote.options(num_gpus=1 if k == "gpu" else 0, **opts).remote(b)
                       for k, b in zip(self.kinds, self.requested)]
        self._info: list | None = None
        # per actor: chunks and rigs scored, seconds inside msog_batch, rate (rigs/s, last chunk, round trip)
        self.stats = [{"chunks": 0, "rigs": 0, "seconds": 0.0, "rate": None} for _ in self.actors]

    def info(self) -> list[dict]:
        """Each actor's backend, host, pid and GPU (starts the actors; raises if one cannot start)."""
        if self._info is None:
            refs = [a.info.remote() for a in self.actors]
            self._info = [self._get(r, i, "starting") for i, r in enumerate(refs)]
            for d, k in zip(self._info, self.kinds):
                d["kind"] = k
        return self._info

    def _get(self, ref, i: int, what: str):
        try:
            return self._ray.get(ref)
        except Exception as e:           # RayTaskError wraps the actor's exception; RayActorError a dead actor
            desc = f"{self.kinds[i]} actor {i}"
            if self._info is not None:
                desc += f" ({self._info[i]['backend']} on {self._info[i]['host']}, pid {self._info[i]['pid']})"
            else:
                desc += f" (backend {self.requested[i]!r})"
            cause = getattr(e, "cause", None)
            if isinstance(cause, Exception):      # the actor's own exception, raised in the method
                text = f"{type(cause).__name__}: {cause}"
            else:                                  # a Ray error holding a traceback: its last line is the cause
                lines = [ln for ln in str(e).strip().splitlines() if ln.strip()]
                text = lines[-1].strip() if lines else type(e).__name__
            raise ActorScoringError(f"{desc} failed {what}: {text}") from e

    def warm(self, spec, lidar, poses, occlusion: str = "sog", task: str = "seg", normalisation: str = "paper") -> None:
        """Load the P-SOG and compile the kernels in every actor (one rig each), before timing."""
        self.info()
        refs = [a.score.remote(spec, lidar, poses[:1], occlusion, task, normalisation) for a in self.actors]
        for i, r in enumerate(refs):
            self._get(r, i, "warming up")

    def _worth_it(self, i: int, n: int, left: int) -> bool:
        return worth_dispatching(n, self.stats[i]["rate"], [s["rate"] for j, s in enumerate(self.stats) if j != i],
                                 left)

    def score(self, spec, lidar, poses, occlusion: str = "sog", task: str = "seg",
              chunk: int | None = None, normalisation: str = "paper") -> np.ndarray:
        """M-SOG of each rig of ``poses`` (P, L, 6), in candidate order.

        Args:
            spec: the ``PSOGSpec`` (resolved: backend name and cache folder fixed in the driver).
            lidar: LiDAR name or model; occlusion, task, normalisation: as ``msog_batch``.
            chunk: rigs per chunk (default: one chunk per actor when all are GPU actors, since every
                round trip costs a GPU actor a fixed overhead: on two GPUs, a large population in two chunks
                took about half the time of one GPU actor (bench/README.md, "What the studies found",
                populations on Ray actors); with CPU actors in the pool the batch is cut into 4 chunks
                per actor, small enough for a slow actor to help without holding up the batch).

        Raises:
            ActorScoringError: an actor failed; the message names it and the chunk's candidates.
        """
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim == 2:
            poses = poses[None]
        P = len(poses)
        if P == 0:
            return np.zeros(0)
        self.info()                     # once: an actor that cannot start fails here, and errors name host and pid
        n_act = len(self.actors)
        per_actor = 1 if all(k == "gpu" for k in self.kinds) else 4
        size = int(chunk) if chunk else (P if n_act == 1 else -(-P // (per_actor * n_act)))
        queue = [(k, s) for k, s in enumerate(range(0, P, max(1, size)))]
        out: list = [None] * len(queue)
        inflight: dict = {}             # ObjectRef -> (actor, chunk index, first candidate, submit time)
        idle = list(range(len(self.actors)))
        while queue or inflight:
            left = sum(min(size, P - s) for _, s in queue)
            # rigs the busy actors hold: they finish those before they could take a queued chunk
            busy = sum(min(size, P - s) for _, _, s, _ in inflight.values())
            for i in sorted(idle, key=lambda j: -(self.stats[j]["rate"] or np.inf)):
                if not queue:
                    break
                k, s = queue[0]
                n = min(size, P - s)
                if inflight and not self._worth_it(i, n, left + busy):
                    continue
                queue.pop(0)
                left -= n
                busy += n
                idle.remove(i)
                ref = self.actors[i].score.remote(spec, lidar, poses[s:s + n], occlusion, task, normalisation)
                inflight[ref] = (i, k, s, time.perf_counter())
            done, _ = self._ray.wait(list(inflight), num_returns=1)
            i, k, s, t0 = inflight.pop(done[0])
            n = min(size, P - s)
            scores, secs = self._get(done[0], i, f"scoring candidates {s}-{s + n - 1}")
            out[k] = scores
            st = self.stats[i]
            st["chunks"] += 1
            st["rigs"] += n
            st["seconds"] += secs
            # the rate includes the round trip (poses out, scores back): what the driver waits for
            st["rate"] = n / max(time.perf_counter() - t0, 1e-9)
            idle.append(i)
        return np.concatenate(out)

    def shutdown(self) -> None:
        """End the actors (their GPUs and CPUs go back to the cluster)."""
        for a in self.actors:
            try:
                self._ray.kill(a)
            except Exception:            # already dead or the cluster is gone: nothing left to free
                pass
        self.actors = []
