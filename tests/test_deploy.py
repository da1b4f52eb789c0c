"""``prefect deploy`` of ``deploy/prefect.yaml`` against a real local Prefect server started by
the test (temporary PREFECT_HOME and SQLite database, 127.0.0.1 only): both deployments are
created on their work pools and the nightly May–October cron schedules read back."""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

pytest.importorskip("prefect")

REPO = Path(__file__).resolve().parents[1]
PREFECT = str(Path(sys.executable).with_name("prefect"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def prefect_server(tmp_path_factory):
    """``prefect server start`` on a free port; yields the environment that talks to it."""
    if not Path(PREFECT).exists():
        pytest.skip("the prefect command is not installed beside this Python")
    home = tmp_path_factory.mktemp("prefect-server-home")
    port = _free_port()
    env = {
        **os.environ,
        "PREFECT_HOME": str(home),
        "PREFECT_API_DATABASE_CONNECTION_URL": f"sqlite+aiosqlite:///{home}/prefect.db",
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "PREFECT_SERVER_UI_ENABLED": "false",
        "PREFECT_LOGGING_LEVEL": "WARNING",
    }
    env.pop("PREFECT_API_URL", None)
    log = open(home / "server.log", "wb")
    proc = subprocess.Popen(
        [PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(port)],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    api = f"http://127.0.0.1:{port}/api"
    try:
        deadline = time.monotonic() + 90
        while True:
            if proc.poll() is not None:
                raise RuntimeError((home / "server.log").read_text()[-3000:])
            try:
                urllib.request.urlopen(f"{api}/health", timeout=1).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError("prefect server did not answer within 90 s") from None
                time.sleep(0.3)
        yield {**env, "PREFECT_API_URL": api}
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=15)
        log.close()


def _prefect(env: dict, *args: str, timeout: float = 180) -> str:
    out = subprocess.run(
        [PREFECT, *args], env=env, cwd=REPO, capture_output=True, text=True, timeout=timeout
    )
    assert out.returncode == 0, f"prefect {' '.join(args)} failed:\n{out.stdout}\n{out.stderr}"
    return out.stdout


def test_prefect_deploy_creates_both_deployments_and_schedule(prefect_server, tmp_path):
    env = {
        **prefect_server,
        "CROPCRAFT_HOME": str(REPO),
        "CROPCRAFT_SITE": "plotA",
        "CROPCRAFT_CROP": "soybean",
    }
    for pool in ("cropcraft-cpu", "cropcraft-gpu"):
        _prefect(env, "work-pool", "create", pool, "--type", "process", "--overwrite")
    _prefect(env, "--no-prompt", "deploy", "--prefect-file", "deploy/prefect.yaml", "--all")

    season = json.loads(
        _prefect(env, "deployment", "inspect", "process-season/field-season", "--output", "json")
    )
    assert season["work_pool_name"] == "cropcraft-cpu"
    assert season["entrypoint"] == "flows/season.py:process_season"
    assert season["parameters"]["site"] == "plotA" and season["parameters"]["crop"] == "soybean"
    crons = [s["schedule"].get("cron") for s in season["schedules"]]
    # nightly May-October, and 1 November: 31 October's photos wait one night, not till May
    assert sorted(crons) == ["0 2 * 5-10 *", "0 2 1 11 *"]
    assert all(s["active"] is True for s in season["schedules"])

    scene = json.loads(
        _prefect(env, "deployment", "inspect", "reconstruct-scene/scene", "--output", "json")
    )
    assert scene["work_pool_name"] == "cropcraft-cpu"
    assert scene["entrypoint"] == "flows/scene.py:reconstruct_scene"
    assert not scene["schedules"]

    dask = json.loads(
        _prefect(env, "deployment", "inspect", "process-scene/scene-dask", "--output", "json")
    )
    assert dask["entrypoint"] == "flows/scene.py:process_scene"
    assert dask["parameters"] == {"runner": "dask"}

    gpu = json.loads(
        _prefect(
            env, "deployment", "inspect", "reconstruct-scene/scene-nerfacto", "--output", "json"
        )
    )
    assert gpu["work_pool_name"] == "cropcraft-gpu"
    assert gpu["parameters"] == {"surfaces_backend": "nerfacto"}
    # a run given its own overrides keeps the deployment's backend: Prefect merges a run's
    # parameters into the deployment's one level deep (overrides would replace a whole dict)
    out = _prefect(
        env, "deployment", "run", "reconstruct-scene/scene-nerfacto",
        "--param", "site=plotA", "--param", "crop=soybean", "--param", "date=2026-07-01",
        "--param", 'overrides={"fit.n_seeds": 2}',
    )  # fmt: skip
    run_id = re.search(r"UUID:\s*([0-9a-f-]{36})", out).group(1)
    params = json.loads(_prefect(env, "flow-run", "inspect", run_id, "--output", "json"))[
        "parameters"
    ]
    assert params["surfaces_backend"] == "nerfacto" and params["overrides"] == {"fit.n_seeds": 2}
    from flows.scene import resolve_config, with_backend

    cfg = resolve_config("soybean", with_backend(params["overrides"], params["surfaces_backend"]))
    assert cfg["surfaces"]["backend"] == "nerfacto" and cfg["fit"]["n_seeds"] == 2

    bench = json.loads(
        _prefect(env, "deployment", "inspect", "benchmark/accuracy", "--output", "json")
    )
    assert bench["entrypoint"] == "flows/benchmark.py:benchmark"
    assert bench["parameters"] == {"crop": "soybean", "quick": True}

    # every flow run pins the CPU kernels as the CLI does (its file loads numpy before `flows`)
    from cropcraft_core.kernels import PORTABLE

    for d in (season, scene, dask, gpu, bench):
        assert d["job_variables"]["env"] == PORTABLE, d["name"]


def test_compose_and_images_reference_the_pools():
    compose = (REPO / "docker" / "compose.yaml").read_text()
    for needle in ("prefect server start", "minio", "cropcraft-cpu", "Dockerfile.cpu"):
        assert needle in compose
    cuda = (REPO / "docker" / "Dockerfile.cuda").read_text()
    assert "nerfstudio" in cuda
    # the CUDA image installs CropCraft with --no-deps (its torch is CUDA's): every other
    # dependency must be in its own list (scikit-optimize, threadpoolctl and psutil were not)
    import re
    import tomllib

    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    names = {re.split(r"[<>=!~\[ ]", d, maxsplit=1)[0].lower() for d in deps}
    listed = cuda[cuda.index("pip install --no-deps .") :].split("CMD")[0].lower()
    replaced = {"torch": "torch==2.5.1", "open3d-cpu": "open3d==0.20.0"}
    for name in sorted(names):
        assert re.search(rf"[\s\"]{re.escape(replaced.get(name, name))}[\s\"<>=]", listed) or (
            name in replaced and replaced[name] in cuda
        ), f"{name} is not installed in Dockerfile.cuda"
    if shutil.which("docker") is None:
        return
    probe = subprocess.run(["docker", "compose", "version"], capture_output=True, text=True)
    if probe.returncode != 0:
        return  # docker without the compose plugin: the text checks above must do
    out = subprocess.run(
        ["docker", "compose", "-f", str(REPO / "docker" / "compose.yaml"), "config", "-q"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
