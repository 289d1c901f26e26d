"""Where the Dask workers come from: a cluster configuration (YAML) and the client for it.

::

    kind: slurm                 # local | slurm | pbs | scheduler
    workers: 16                 # worker processes (or: adaptive: {minimum: 2, maximum: 64})
    cores: 8                    # local: cores of each worker; slurm/pbs: cores of each job
    processes: 4                # slurm/pbs: worker processes per job (each cores/processes)
    memory: 32GiB               # local: of each worker; slurm/pbs: of each job
    walltime: "04:00:00"
    queue: cpu                  # SLURM partition / PBS queue
    account: mylab
    job_extra_directives: ["--exclusive"]
    job_script_prologue: ["module load python"]
    local_directory: /scratch/$USER/dask
    env: {ANNY_CACHE_DIR: /shared/anny}
    python: /shared/repo/.venv/bin/python
    address: tcp://head:8786    # kind: scheduler (join a running cluster)

Every worker runs one task at a time (one thread: the stages are Python-heavy and start their
own process pools), declares the resources ``cores`` and ``memory_gb`` that the executor
requests per stage (``Stage.cores``, ``Stage.memory_gb``), is not daemonic
(``distributed.worker.daemon: False``: a stage's process pool needs children), and gets
``PIPELINE_LOCKS``: ``flock`` on a LocalCluster (one host: the kernel's locks hold, and a
killed worker's goes at once), ``lease`` on SLURM/PBS/a joined scheduler (locks that hold
across hosts on a shared filesystem; ``env`` overrides either), one BLAS thread
(``OMP_NUM_THREADS=1`` ...), ``PYTHONPATH`` with this repository, and ``env``.

``load_cluster_config(path)`` validates (errors name the file and the field),
``make_client(config)`` starts the cluster (``distributed.LocalCluster``,
``dask_jobqueue.SLURMCluster``/``PBSCluster``, or ``Client(address)``), ``job_script(config)``
is the batch script dask-jobqueue would submit for each job (nothing submitted):
``python -m pipeline cluster-script --cluster recipes/cluster/slurm.yaml``.
"""
from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

REPO = Path(__file__).resolve().parents[1]
# constants
ALLOWED_FAILURES = 3          # a task whose worker dies this often is failed (KilledWorker)
PLACEHOLDER_SCHEDULER = "tcp://SCHEDULER:8786"  # in a job script printed without a cluster
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: Variables Dask's nanny would set before spawning a worker (``distributed.nanny.
#: pre-spawn-environ``, also in the nanny's own process: a LocalCluster's nannies live in ours,
#: so every process we start afterwards inherits them) that we leave unset.
#: ``MALLOC_TRIM_THRESHOLD_=65536`` turns off glibc's dynamic mmap threshold, so every array
#: over 128 kB is mapped and unmapped afresh: the partner fit's Jacobian blocks took 2.8x the
#: CPU in a Dask worker (demo Handshake, the same fit bit for bit: ``extra_jacobian_s`` 245
#: against 89 s serial; session 37), a numpy loop of 2.5 MB temporaries 19.3 against 14.0 CPU-s.
#: Set in this process's Dask config (:func:`_dask_config`): the local nannies read it; a
#: SLURM/PBS job's own nanny reads its own config and still sets it (not unset there yet).
NO_PRE_SPAWN = ("MALLOC_TRIM_THRESHOLD_",)
# the lock backend of the workers (pipeline.store): on one host the kernel's flock holds and a
# killed worker's lock goes at once; across hosts (a shared NFS/Lustre folder) only leases do
LOCKS_BY_KIND = {"local": "flock", "slurm": "lease", "pbs": "lease", "scheduler": "lease"}


class ClusterConfigError(ValueError):
    """A cluster configuration that can't be used; the message reads ``file: field: what``."""

    def __init__(self, file: Path | str, field: str, message: str):
        self.file, self.field = str(file), field
        super().__init__(f"{file}: {field}: {message}")


class Adaptive(BaseModel):
    model_config = ConfigDict(extra="forbid")
    minimum: int = Field(1, ge=0)
    maximum: int = Field(..., ge=1)

    @model_validator(mode="after")
    def _order(self):
        if self.minimum > self.maximum:
            raise ValueError(f"minimum {self.minimum} > maximum {self.maximum}")
        return self


class ClusterConfig(BaseModel):
    """A validated cluster configuration (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["local", "slurm", "pbs", "scheduler"] = "local"
    workers: int | None = Field(None, ge=1)
    adaptive: Adaptive | None = None
    cores: int = Field(1, ge=1)
    processes: int = Field(1, ge=1)
    memory: str | None = None
    walltime: str | None = None
    queue: str | None = None
    account: str | None = None
    job_extra_directives: list[str] = []
    job_script_prologue: list[str] = []
    local_directory: str | None = None
    env: dict[str, str] = {}
    python: str | None = None
    address: str | None = None
    allowed_failures: int = Field(ALLOWED_FAILURES, ge=0)
    dashboard_address: str | None = ":8787"
    source: str = "<cluster config>"

    @field_validator("memory")
    @classmethod
    def _memory(cls, v):
        if v is None:
            return v
        from dask.utils import parse_bytes

        try:
            if parse_bytes(v) <= 0:
                raise ValueError
        except (ValueError, TypeError):
            raise ValueError(f"{v!r} is not an amount of memory (e.g. 8GiB)") from None
        return v

    @field_validator("env", mode="before")
    @classmethod
    def _env(cls, v):
        if isinstance(v, dict):
            return {str(k): str(x) for k, x in v.items()}
        return v

    @model_validator(mode="after")
    def _consistent(self):
        if self.workers is not None and self.adaptive is not None:
            raise ValueError("workers: give either workers or adaptive, not both")
        if self.kind == "scheduler" and not self.address:
            raise ValueError("address: kind scheduler needs the scheduler's address")
        if self.kind in ("slurm", "pbs"):
            if self.memory is None:
                raise ValueError(f"memory: kind {self.kind} needs the memory of a job (e.g. 16GiB)")
            if self.cores % self.processes:
                raise ValueError(f"processes: {self.processes} does not divide cores {self.cores}")
        return self

    # -- per worker ---------------------------------------------------------------------------
    def worker_cores(self) -> int:
        return self.cores // self.processes if self.kind in ("slurm", "pbs") else self.cores

    def worker_memory_bytes(self, n_local: int = 1) -> int:
        from dask.utils import parse_bytes

        if self.memory is not None:
            total = parse_bytes(self.memory)
            return total // self.processes if self.kind in ("slurm", "pbs") else total
        return _total_memory() // max(n_local, 1)

    def n_workers(self) -> int:
        if self.workers is not None:
            return self.workers
        if self.adaptive is not None:
            return self.adaptive.minimum
        return max((os.cpu_count() or 1) // self.cores, 1) if self.kind == "local" else 1


def _total_memory() -> int:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def load_cluster_config(path: Path | str) -> ClusterConfig:
    """Read and validate a cluster YAML. ClusterConfigError naming file and field."""
    path = Path(path)
    if not path.is_file():
        raise ClusterConfigError(path, "(file)", "not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ClusterConfigError(path, "(file)", f"not YAML: {e}") from None
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ClusterConfigError(path, "(file)", f"expected a mapping, got {type(raw).__name__}")
    return config_from_dict(raw, path)


def config_from_dict(raw: dict, source: Path | str = "<cluster config>") -> ClusterConfig:
    try:
        return ClusterConfig.model_validate({**raw, "source": str(source)})
    except ValidationError as e:
        err = e.errors()[0]
        loc = ".".join(str(p) for p in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        if not loc and ":" in msg:  # a model-level check names its field first
            loc, msg = (s.strip() for s in msg.split(":", 1))
        got = err.get("input")
        got_s = "" if isinstance(got, (dict, list)) or not loc else f" (got {got!r})"
        raise ClusterConfigError(source, loc or "(file)", f"{msg}{got_s}") from None


def worker_env(config: ClusterConfig) -> dict[str, str]:
    """The environment every worker starts with (``config.env`` wins)."""
    parts = [os.path.abspath(p) for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    pp = os.pathsep.join(dict.fromkeys([str(REPO), *parts]))  # this repository first, absolute
    return {**WORKER_ENV, "PIPELINE_LOCKS": LOCKS_BY_KIND.get(config.kind, "lease"),
            "PYTHONPATH": pp, "DASK_DISTRIBUTED__WORKER__DAEMON": "False", **config.env}


def worker_resources(config: ClusterConfig, n_local: int | None = None) -> dict[str, float]:
    """``{"cores", "memory_gb"}`` each worker declares."""
    n = config.n_workers() if n_local is None else n_local
    return {"cores": float(config.worker_cores()),
            "memory_gb": round(config.worker_memory_bytes(n) / 2**30, 3)}


def _resources_arg(res: dict[str, float]) -> str:
    return ",".join(f"{k}={v:g}" for k, v in res.items())


def _dask_config(config: ClusterConfig) -> None:
    """Settings read in this process by the scheduler and the local nannies (set globally: a
    nanny that restarts a killed worker reads them again)."""
    import dask

    dask.config.set({"distributed.worker.daemon": False,
                     "distributed.scheduler.allowed-failures": config.allowed_failures,
                     **{f"distributed.nanny.pre-spawn-environ.{k}": None for k in NO_PRE_SPAWN}})


def _jobqueue_kwargs(config: ClusterConfig) -> dict[str, Any]:
    res = worker_resources(config)
    env = worker_env(config)
    prologue = [f"export {k}={shlex.quote(v)}" for k, v in env.items()]
    prologue += list(config.job_script_prologue)
    kw: dict[str, Any] = dict(
        cores=config.cores, processes=config.processes, memory=config.memory,
        walltime=config.walltime, queue=config.queue, account=config.account,
        job_extra_directives=list(config.job_extra_directives), job_script_prologue=prologue,
        python=config.python or sys.executable,
        # one thread per worker process (the last --nthreads wins over dask-jobqueue's own)
        worker_extra_args=["--nthreads", "1", "--resources", _resources_arg(res)],
    )
    if config.local_directory:
        kw["local_directory"] = config.local_directory
    return {k: v for k, v in kw.items() if v is not None}


def _job_class(kind: str):
    if kind == "slurm":
        from dask_jobqueue.slurm import SLURMJob

        return SLURMJob
    from dask_jobqueue.pbs import PBSJob

    return PBSJob


def job_script(config: ClusterConfig, scheduler: str = PLACEHOLDER_SCHEDULER) -> str:
    """The batch script dask-jobqueue submits for one job of ``config`` (slurm or pbs), with
    ``scheduler`` as the address the workers connect to. Nothing is submitted."""
    if config.kind not in ("slurm", "pbs"):
        raise ClusterConfigError(config.source, "kind", f"{config.kind}: no job script "
                                 "(only slurm and pbs submit jobs)")
    job = _job_class(config.kind)(scheduler=scheduler, name="dask-worker",
                                  **_jobqueue_kwargs(config))
    return job.job_script()


def make_client(config: ClusterConfig, workers: int | None = None):
    """Start (or join) the cluster of ``config``; ``workers`` overrides its worker count.
    Returns ``(client, cluster, dashboard_link)``; ``cluster`` is None for kind scheduler.
    Close both when done (``client.close(); cluster.close()``)."""
    from distributed import Client

    _dask_config(config)
    if config.kind == "scheduler":
        client = Client(config.address)
        return client, None, client.dashboard_link
    n = workers or config.n_workers()
    if config.kind == "local":
        from distributed import LocalCluster

        kw: dict[str, Any] = dict(
            n_workers=n, threads_per_worker=1, processes=True,
            resources=worker_resources(config, n), env=worker_env(config),
            memory_limit=config.worker_memory_bytes(n), dashboard_address=config.dashboard_address,
        )
        if config.local_directory:
            kw["local_directory"] = config.local_directory
        cluster = LocalCluster(**kw)
        if config.adaptive is not None and workers is None:
            cluster.adapt(minimum=config.adaptive.minimum, maximum=config.adaptive.maximum)
    else:
        if config.kind == "slurm":
            from dask_jobqueue import SLURMCluster as Cluster
        else:
            from dask_jobqueue import PBSCluster as Cluster
        cluster = Cluster(scheduler_options={"dashboard_address": config.dashboard_address},
                          **_jobqueue_kwargs(config))
        if config.adaptive is not None and workers is None:
            cluster.adapt(minimum=config.adaptive.minimum, maximum=config.adaptive.maximum)
        else:
            cluster.scale(n=n)
    client = Client(cluster)
    return client, cluster, client.dashboard_link
