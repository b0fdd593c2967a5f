"""Running study tasks on a Ray cluster (the optional ``ray`` extra).

Every node of the cluster needs probegym installed (``pip install -e ".[ray]"`` in the same
environment) and, for the published scene, the scene directory at the same path.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from tissue import ConfigError


def _call(function: Callable[..., Any], *args: Any) -> Any:
    return function(*args)


def ray_submitter(address: str, workers: int, cpus_per_task: int = 1) -> Callable[..., Future[Any]]:
    """A ``submit(function, *args) -> Future`` running tasks on the cluster at ``address``.

    ``address`` is a Ray address (``ray://host:10001``, ``host:6379``), ``auto`` (the cluster
    this machine belongs to) or ``local`` (start a private Ray on this machine with
    ``workers`` CPUs). Each task asks for ``cpus_per_task`` CPUs.
    """
    try:
        import ray
    except ImportError:
        raise ConfigError(
            "--ray needs Ray, an optional extra: pip install 'probegym[ray]'"
        ) from None
    if not ray.is_initialized():
        if address == "local":
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        else:
            try:
                ray.init(address=address, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError) as error:
                raise ConfigError(f"--ray {address}: cannot connect ({error})") from None
    remote = ray.remote(num_cpus=cpus_per_task)(_call)

    def submit(function: Callable[..., Any], *args: Any) -> Future[Any]:
        return remote.remote(function, *args).future()

    return submit
