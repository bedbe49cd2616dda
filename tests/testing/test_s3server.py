"""The local S3 server's handle (streamsvd.testing.s3server), without moto."""

import subprocess
import sys

from streamsvd.testing.s3server import S3Server


def test_environment_points_at_the_endpoint_and_stop_ends_the_process():
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    server = S3Server(process, "http://127.0.0.1:1")
    env = server.environment()
    assert env["AWS_ENDPOINT_URL"] == "http://127.0.0.1:1"
    assert {"AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION"} <= set(env)
    server.stop()
    assert process.poll() is not None
