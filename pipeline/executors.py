"""How the nodes of a plan get run.

An executor receives the plan's nodes in DAG order and a ``run_node(node, done)`` callable,
where ``done`` maps the ids of finished nodes to their :class:`Outcome`; it must call
``run_node`` for a node only after all of ``node.upstream_ids()`` are in ``done``.
``run_node`` does the cache check, the locking and the atomic write itself, so it is safe to
call from several processes or machines that share the ``outputs`` folder. When SIGTERM or
SIGINT interrupts a stage, ``run_node`` raises :class:`pipeline.procs.Interrupted` (a
``SystemExit``) after cleaning up: an executor lets it through (no further node starts).
Signal handlers can only be set in the main thread, so an executor running nodes in other
threads gets no such cleanup for them; one running them in child processes should start
those with :func:`pipeline.procs.die_with_parent`.

Only :class:`SerialExecutor` exists today. The seam for scale-out: a ``DaskExecutor`` would
submit ``run_node`` per node to a ``dask.distributed`` client with the upstream futures as
dependencies (the artifact locks already make concurrent workers safe), and collect the
outcomes into the same dict.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Mapping, Protocol

if TYPE_CHECKING:
    from pipeline.plan import Node, NodeId

STATUSES = ("hit", "computed", "failed", "skipped", "planned")


@dataclass(frozen=True)
class Outcome:
    """What happened to one node. ``status``: ``hit`` (cached artifact reused), ``computed``,
    ``failed`` (``detail`` holds the traceback), ``skipped`` (an upstream is unavailable),
    ``planned`` (the stage is not implemented). ``seconds``: wall time spent on the node."""

    status: str
    seconds: float = 0.0
    detail: str = ""

    @property
    def ok(self) -> bool:
        return self.status in ("hit", "computed")


RunNode = Callable[["Node", Mapping["NodeId", Outcome]], Outcome]


class Executor(Protocol):
    def run(self, nodes: list["Node"], run_node: RunNode) -> dict["NodeId", Outcome]: ...


class SerialExecutor:
    """Runs the nodes one after the other in the given (topological) order."""

    def run(self, nodes: list["Node"], run_node: RunNode) -> dict["NodeId", Outcome]:
        done: dict = {}
        for n in nodes:
            done[n.id] = run_node(n, done)
        return done
