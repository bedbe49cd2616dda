"""The set-up the cluster tests share: the S3 server's variables and the workers' environment.

The client (this process) reaches the moto S3 server through the ``AWS_*`` variables of
:func:`s3_environment`; the ``dask worker`` processes get theirs from
:func:`workers_environment`, never from the task graph.
"""

import os

import pytest


@pytest.fixture(scope="module")
def s3_environment(s3_server):
    """Point this process at the S3 server for the module; yield its ``AWS_*`` variables.

    The variables this process had before are restored after the module.
    """
    env = s3_server.environment()
    with pytest.MonkeyPatch.context() as patch:
        for key, value in env.items():
            patch.setenv(key, value)
        yield env


@pytest.fixture(scope="session")
def workers_environment():
    """Return a function that makes the environment of worker processes.

    ``workers_environment(**aws)`` is this process's environment without its ``AWS_*``
    variables, and with ``aws`` (the workers' own credentials and endpoint) instead.
    """

    def environment(**aws: str) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
        env.update(aws)
        return env

    return environment
