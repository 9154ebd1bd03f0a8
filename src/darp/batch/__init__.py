"""darp.batch: batches of surveys on one machine or a Ray cluster (``darp process --executor ray[:ADDRESS]``,
``darp twin generate``).

The executor (:mod:`.executor`: a loop, or one Ray Core task per survey), each survey in a fresh process forked
from a preloaded forkserver (:mod:`.fresh`) with its thread limits (:mod:`.threads`); the per-survey work is
:mod:`.tasks` (processing) and :mod:`.generate` (twin surveys). Ray loads only when a Ray executor runs.
"""

from __future__ import annotations

from darp.lazy import LazyExports

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing

_lazy = LazyExports(__name__, {
    ".executor": ("Executor", "parse_executor", "run_tasks"),
    ".tasks": ("process_batch", "process_one"),
    ".generate": ("SurveySpec", "generate_batch", "plan_surveys"),
    ".fresh": ("ChildCrashed", "call_in_fresh_process"),
})
__getattr__ = _lazy.attribute
__dir__ = _lazy.names

if TYPE_CHECKING:
    from darp.batch.executor import Executor, parse_executor, run_tasks
    from darp.batch.fresh import ChildCrashed, call_in_fresh_process
    from darp.batch.generate import SurveySpec, generate_batch, plan_surveys
    from darp.batch.tasks import process_batch, process_one

__all__ = [
    "ChildCrashed",
    "Executor",
    "SurveySpec",
    "call_in_fresh_process",
    "generate_batch",
    "parse_executor",
    "plan_surveys",
    "process_batch",
    "process_one",
    "run_tasks",
]
