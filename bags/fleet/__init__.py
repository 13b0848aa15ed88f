"""Fleet scale: many bags replayed, or many drives rendered, as tasks of a Ray runtime (local or a
cluster; the ``fleet`` extra). Ray itself is imported only when tasks run.

Public names: :func:`evaluate` with :class:`EvaluateOptions` and :class:`EvaluateResult`
(``bev-bag evaluate``: bags replayed as tasks, their scores added up exactly by
:func:`aggregate`), and the task runner of :mod:`~bags.fleet.ray_tasks` that ``bev-bag
synth-many`` uses too: :class:`RayOptions`, :func:`add_ray_args`, :func:`ray_runtime`,
:func:`run_tasks`, :class:`TaskFailure`.
"""

from .evaluate import EvaluateOptions, EvaluateResult, evaluate
from .ray_tasks import RayOptions, TaskFailure, add_ray_args, ray_runtime, run_tasks
from .replay_tasks import aggregate

__all__ = ["EvaluateOptions", "EvaluateResult", "RayOptions", "TaskFailure", "add_ray_args", "aggregate", "evaluate",
           "ray_runtime", "run_tasks"]
