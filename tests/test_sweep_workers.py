"""A sweep's process pool when a worker process dies: the jobs say so, and the error names the likely causes, the
main-module guard among them (a script without it starts the sweep again in every worker)."""

import os

import pytest

from fcnpose_tf.errors import UserError
from fcnpose_tf.sweep.executors import LocalExecutor
from fcnpose_tf.sweep.jobs import Job


def die(config, job):
    """A job whose worker process ends at once, as one killed by the kernel or failing to bootstrap."""
    os._exit(3)


def test_a_dead_worker_fails_its_jobs_and_names_the_causes():
    events = []
    with pytest.raises(UserError, match=r"a sweep worker process died; .* put the sweep under "
                                        r"`if __name__ == \"__main__\":`"):
        LocalExecutor(workers=2, threads=1).run(die, None, [Job(0), Job(1)], set(), events.append)
    failed = [e for e in events if e.kind == "failed"]
    assert failed and all("a script's code not under `if __name__" in e.error for e in failed)
