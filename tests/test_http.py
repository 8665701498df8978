"""The HTTP service against real processes on 127.0.0.1: `abcns serve` (uvicorn), a stock
`dask scheduler` and two `dask worker` processes.

- the §4.1 job submitted over HTTP, its events followed to the end, equals `abcns run`;
- a worker killed mid-job: identical; the service SIGKILLed mid-job and restarted: the job
  resumes, finishes identical, and its events continue after Last-Event-ID;
- 20 queued jobs and 100 concurrent event-stream clients: every client sees every event;
- tokens (401 / 403), job-id validation, fuzzing the OpenAPI schema (no 5xx).
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
from pathlib import Path

import httpx
import numpy as np
import pytest
from cli_in_process import invoke
from http_helpers import demo_spec, follow, same_populations

from benchmarks.harness import AUTH, BIN, ROOT, TOKEN, Service, StockCluster, duffing_spec

pytestmark = pytest.mark.http


@pytest.fixture(scope="module")
def reference(cluster, tmp_path_factory):
    """The same job run with `abcns run` on the same cluster (in this process: tests/cli_in_process)."""
    tmp = tmp_path_factory.mktemp("cli")
    (tmp / "spec.json").write_text(json.dumps(duffing_spec()))
    invoke("run", tmp / "spec.json", "--out", tmp / "ref.zarr", "--scheduler", cluster.address, "--quiet")
    return tmp / "ref.zarr"


def test_http_job_with_a_worker_killed_equals_abcns_run(private_cluster, tmp_path, reference):
    """On a cluster of its own (a worker is killed), the reference from the shared one."""
    cluster = private_cluster
    service = Service(tmp_path / "jobs", cluster.address)
    try:
        killed_mid_job_equals_reference(service, cluster, reference)
    finally:
        service.close()


def killed_mid_job_equals_reference(service: Service, cluster: StockCluster, reference: Path) -> None:
    r = httpx.post(f"{service.url}/jobs", json=duffing_spec(), headers=AUTH, timeout=60)
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    first = follow(service.url, job_id, until=lambda ev: sum(e["event"] == "population" for e in ev) >= 2)
    victim = cluster.worker_pids()[0]
    os.kill(victim, signal.SIGKILL)  # mid-job; the nanny starts a new worker
    rest = follow(service.url, job_id, after=first[-1]["id"])
    events = first + rest
    assert [e["id"] for e in events] == list(range(1, len(events) + 1))
    assert [e["event"] for e in events[:2]] == ["queued", "started"] and events[-1]["event"] == "finished"
    pops = [e["data"]["population"] for e in events if e["event"] == "population"]
    assert pops == list(range(1, 9))
    assert victim not in cluster.worker_pids()
    same_populations(service_store(service, job_id), reference)
    status = httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()
    assert status["status"] == "finished" and status["progress"]["population"] == 8
    result = httpx.get(f"{service.url}/jobs/{job_id}/result", headers=AUTH).json()
    assert result["stop_reason"] == "max_populations" and len(result["epsilon"]) == 8
    pop = httpx.get(f"{service.url}/jobs/{job_id}/populations/8", headers=AUTH).json()
    assert len(pop["distances"]) == 500 and pop["epsilon"] == result["epsilon"][-1]


def service_store(service: Service, job_id: str) -> Path:
    return service.job_dir(job_id) / "store.zarr"


def test_service_sigkilled_mid_job_resumes_identical_and_events_continue(fresh, reference):
    service = fresh
    job_id = httpx.post(f"{service.url}/jobs", json=duffing_spec(), headers=AUTH, timeout=60).json()["id"]
    before = follow(service.url, job_id, until=lambda ev: sum(e["event"] == "population" for e in ev) >= 3)
    service.kill()  # the job's loop runs on a worker: it stops at its next batch (its task released), or ends
    service.start()  # same store directory: the job is listed and resumed
    after = follow(service.url, job_id, after=before[-1]["id"])
    events = before + after
    assert [e["id"] for e in events] == list(range(1, len(events) + 1))  # ids continue, none lost or repeated
    # a start after the kill is a resume; there is none when the loop, on its worker, ended the
    # job while the service was down (the restarted service reads it finished from its store)
    assert all(e["data"]["resumed"] for e in after if e["event"] == "started")
    pops = [e["data"]["population"] for e in events if e["event"] == "population"]
    assert sorted(set(pops)) == list(range(1, 9)) and events[-1]["event"] == "finished"
    same_populations(service_store(service, job_id), reference)


def test_twenty_jobs_and_a_hundred_event_clients(cluster, tmp_path):
    service = Service(tmp_path / "jobs", cluster.address, max_running=2)
    try:
        ids = [httpx.post(f"{service.url}/jobs", json=demo_spec(seed), headers=AUTH, timeout=60).json()["id"]
               for seed in range(20)]

        async def client(job_id: str) -> list[tuple[int, str]]:
            seen = []
            async with httpx.AsyncClient(timeout=600) as http:
                async with http.stream("GET", f"{service.url}/jobs/{job_id}/events", headers=AUTH) as r:
                    assert r.status_code == 200
                    event = None
                    async for line in r.aiter_lines():
                        if line.startswith("event:"):
                            event = line.split(":", 1)[1].strip()
                        elif line.startswith("id:"):
                            seen.append((int(line.split(":", 1)[1]), event))
                            if event in ("finished", "failed", "cancelled"):
                                return seen
            return seen

        async def main():
            return await asyncio.gather(*(client(ids[i % 20]) for i in range(100)))

        results = asyncio.run(main())
        for i, seen in enumerate(results):
            job_id = ids[i % 20]
            assert seen[-1][1] == "finished", (job_id, seen)
            assert [k for k, _ in seen] == list(range(1, len(seen) + 1))
            assert [e for _, e in seen] == ["queued", "started", "placed", "population", "population", "population",
                                            "finished"]
        listed = httpx.get(f"{service.url}/jobs", params={"status": "finished"}, headers=AUTH).json()
        assert {j["id"] for j in listed} >= set(ids)
    finally:
        service.close()


def test_tokens_ids_and_bad_specs(service):
    assert httpx.get(f"{service.url}/jobs").status_code == 401
    assert httpx.get(f"{service.url}/jobs", headers={"Authorization": "Bearer wrong"}).status_code == 403
    assert httpx.get(f"{service.url}/health").status_code == 200
    icon = httpx.get(f"{service.url}/favicon.ico")  # the browser's own request, without the token (AA, point 4)
    assert icon.status_code == 200 and icon.headers["content-type"].startswith("image/svg+xml")
    assert httpx.get(f"{service.url}/jobs/..%2F..%2Fetc", headers=AUTH).status_code in (404, 422)
    assert httpx.get(f"{service.url}/jobs/{'0' * 32}", headers=AUTH).status_code == 404
    bad = duffing_spec()
    bad["models"][0]["simulator"] = "os:system"  # no code over the wire
    r = httpx.post(f"{service.url}/jobs", json=bad, headers=AUTH, timeout=60)
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "models[0].simulator"
    bad = duffing_spec()
    bad["data"]["observed"] = "/etc/passwd"  # no files over HTTP
    r = httpx.post(f"{service.url}/jobs", json=bad, headers=AUTH, timeout=60)
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "data.observed"
    bad = duffing_spec()
    bad["data"]["observed"][7] = None  # a null inline (AA, point 8): its sample first, not pydantic's str branch
    r = httpx.post(f"{service.url}/jobs", json=bad, headers=AUTH, timeout=60)
    first = r.json()["detail"][0]
    assert r.status_code == 422 and first["field"] == "data.observed[7]" and "sample 7 (counting from 0)" in first["msg"]
    huge = {"x": "a" * (40 * 1024 * 1024)}
    assert httpx.post(f"{service.url}/jobs", json=huge, headers=AUTH, timeout=60).status_code == 413


def test_upload_npz(service, tmp_path):
    folder = ROOT / "examples" / "duffing_41"
    np.savez(tmp_path / "data.npz", force=np.load(folder / "force.npy"), x=np.load(folder / "displacement.npy"))
    spec = duffing_spec(max_populations=1)
    spec["data"].update(input="npz:force", observed="npz:x")
    with (tmp_path / "data.npz").open("rb") as f:
        r = httpx.post(f"{service.url}/jobs/upload", data={"spec": json.dumps(spec)}, files={"data": f}, headers=AUTH,
                       timeout=60)
    assert r.status_code == 201, r.text
    assert follow(service.url, r.json()["id"])[-1]["event"] == "finished"


def test_fuzzing_the_openapi_schema_gives_no_server_error(fresh, tmp_path):
    """schemathesis over every operation but the (streaming) event endpoint; seeded. Run
    in a temporary directory so its cache of earlier runs (.schemathesis/) stays out of the
    repository and every run starts from the same state; on a service of its own, with no
    job in it: its stateful phase follows links inferred from the answers (a job id to the
    job's routes), so the jobs of other tests would change what it sends."""
    done = subprocess.run(
        [BIN / "schemathesis", "run", f"{fresh.url}/openapi.json", "--checks", "not_a_server_error",
         "--header", f"Authorization: Bearer {TOKEN}", "--max-examples", "30", "--generation-deterministic",
         "--exclude-path-regex", "events", "--request-timeout", "20"],
        capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
