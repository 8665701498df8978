"""Peak memory of the HTTP service through the hostile suite of issue R.

Starts a stock `dask scheduler` with two workers and `abcns serve` (default limits) on
127.0.0.1 and sends it, in this order, what the issue's hostile client sent:

1. bodies that froze it: 900 levels around a million zeros (2 MB), a flat array of 14
   million zeros (29 MB), and a 31 MB spec of 3.9 million numbers inside every limit (it
   is parsed and validated in full), three of each at once;
2. physically invalid specs (fs 1e-300 and 1e308, m = -1 and 0, priors [-1e308, 1e308],
   a force of 2^62);
4. uploads of 2^25-sample records: four longdouble at once (a megabyte each, 512 MB per
   record decompressed) and four float64 with a fit window at once;
5. 30 submissions at once with ABCNS_MAX_QUEUED=3's count of places;
6. 5,000-digit integers, in /jobs and in an upload's spec;
7. duplicate model names;
9. 100 KB headers, 20 event streams dropped mid-stream, and 20 concurrent GET /result of a
   job of 20,000 particles (until its tenth population, then cancelled).

and then, beyond the issue's suite, two uploads at once of whole 2^25-sample records (no
fit window: the largest upload a job may hold at the default limits). Point 3 (a batch
outliving the budget) and 8 (a full disk) cost time or need a fault injected, not memory:
tests/test_http_holds.py covers them. Meanwhile a thread polls /health; the script prints
the answers by status, /health's slowest answer, and the peak resident memory (VmHWM,
reset between phases) of the service process and of the child process that parses
submissions, phase by phase.

    python -m benchmarks.http_hostile
    python -m benchmarks.http_hostile --issue-z   # issue Z's attacks 2, 3, 4, 7, 8 (main_z)
"""

from __future__ import annotations

import asyncio
import collections
import io
import json
import select
import shutil
import socket
import struct
import subprocess
import tempfile
import threading
import time
import zipfile
from pathlib import Path

import httpx
import numpy as np
import psutil

from benchmarks.harness import AUTH, ROOT, Service, StockCluster, duffing_spec, wait_until
from service.run.store import Store


def close_and_count(service, cluster, statuses: collections.Counter, start: float) -> str:
    """Stop the service and its cluster, print the answers by status; the service log's
    error lines."""
    errors = "\n".join(line for line in service.log.read_text().splitlines() if "ERROR" in line or "Traceback" in line)
    service.close()
    cluster.close()
    print(f"{sum(statuses.values())} answers in {time.monotonic() - start:.0f} s: "
          + ", ".join(f"{n} x {s}" for s, n in sorted(statuses.items())))
    return errors


def peak_mb(pid: int) -> float:
    """A process's peak resident memory since its start or the last reset_peak()."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return 0.0


def reset_peak(pid: int) -> None:
    """Reset a process's VmHWM to its current resident memory (Linux: clear_refs, 5)."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def zeros_npz(n: int, dtype: str, head: dict[str, np.ndarray]) -> bytes:
    """An .npz of ``n``-sample records: ``head``, then zeros (deflated: well under a MB)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, first in head.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array_header_1_0(f, {"descr": np.dtype(dtype).str, "fortran_order": False,
                                                         "shape": (n,)})
                f.write(first.astype(dtype).tobytes())
                zeros, left = bytes(16 << 20), (n - first.size) * np.dtype(dtype).itemsize
                while left:
                    f.write(zeros[: min(left, len(zeros))])
                    left -= min(left, len(zeros))
    return buffer.getvalue()


def main() -> None:
    tmp = Path(tempfile.mkdtemp())
    cluster = StockCluster(tmp / "dask")
    service = Service(tmp / "jobs", cluster.address, env={"ABCNS_MAX_QUEUED": "3"})
    statuses: collections.Counter = collections.Counter()
    health: list[float] = []
    done = threading.Event()

    def poll() -> None:
        with httpx.Client(timeout=60) as client:
            while not done.is_set():
                start = time.perf_counter()
                client.get(f"{service.url}/health")
                health.append(time.perf_counter() - start)
                time.sleep(0.05)

    async def at_once(requests) -> None:
        async with httpx.AsyncClient(base_url=service.url, timeout=600, headers=AUTH) as http:
            for r in await asyncio.gather(*(make(http) for make in requests)):
                statuses[r.status_code] += 1
                if r.status_code == 201:
                    await http.delete(f"/jobs/{r.json()['id']}")

    def body(raw: bytes):
        return lambda http: http.post("/jobs", content=raw, headers={"Content-Type": "application/json"})

    def upload(spec: dict | str, npz: bytes, name: str = "spec.json"):
        text = spec if isinstance(spec, str) else json.dumps(spec)
        return lambda http: http.post("/jobs/upload", files={"spec": (name, text.encode()), "data": ("x.npz", npz)})

    poller = threading.Thread(target=poll, daemon=True)
    poller.start()
    start = time.monotonic()
    service_proc = psutil.Process(service.proc.pid)  # type: ignore[union-attr]
    peaks: list[tuple[str, float, float]] = []  # (phase, service MB, parser MB)

    def phase(name: str) -> None:
        """The peaks of the phase before, then a reset for this one."""
        children = service_proc.children(recursive=True)
        if peaks:
            peaks[-1] = (peaks[-1][0], peak_mb(service_proc.pid), max((peak_mb(c.pid) for c in children), default=0.0))
        if name:
            print(name, flush=True)
            for pid in [service_proc.pid, *(c.pid for c in children)]:
                reset_peak(pid)
            peaks.append((name, 0.0, 0.0))

    try:
        phase("1. bodies that froze the service")
        deep = b'{"name":"x","data":' + b"[" * 900 + b",".join([b"0"] * 1_000_000) + b"]" * 900 + b"}"
        wide = b'{"name":"x","data":[' + b",".join([b"0"] * 14_000_000) + b"]}"
        spec = duffing_spec(max_populations=1, particles=200)
        spec["data"].update(input="__A__", observed="__B__")
        numbers = b"[" + b",".join([b"0.123456"] * 1_950_000) + b"]"
        full = json.dumps(spec).encode().replace(b'"__A__"', numbers).replace(b'"__B__"', numbers)
        for raw in (deep, wide, full):
            asyncio.run(at_once([body(raw)] * 3))
        del deep, wide, full, numbers

        phase("2. physically invalid specs")
        changes = [lambda s: s["data"].update(fs=1e-300), lambda s: s["data"].update(fs=1e308),
                   lambda s: s["models"][0]["fixed"].update(m=-1), lambda s: s["models"][0]["fixed"].update(m=0),
                   lambda s: s["models"][0]["priors"].update(k=[-1e308, 1e308]),
                   lambda s: s["data"].update(input=[f * 2.0**62 for f in s["data"]["input"]])]
        for change in changes:
            spec = duffing_spec(max_populations=1, particles=200)
            change(spec)
            asyncio.run(at_once([body(json.dumps(spec).encode())]))

        phase("4. uploads of 2^25-sample records, with a fit window or longdouble")
        folder = ROOT / "examples" / "duffing_41"
        head = {"force": np.load(folder / "force.npy"), "x": np.load(folder / "displacement.npy")}
        spec = duffing_spec(max_populations=1, particles=200)
        spec["data"].update(input="npz:force", observed="npz:x")
        whole = json.loads(json.dumps(spec))
        for key in ("fit", "test"):
            whole["data"].pop(key)
        asyncio.run(at_once([upload(spec, zeros_npz(2**25, "longdouble", head))] * 4))
        asyncio.run(at_once([upload(spec, zeros_npz(2**25, "float64", head))] * 4))

        phase("5. thirty submissions at once")
        asyncio.run(at_once([body(json.dumps(duffing_spec(max_populations=10_000, particles=200)).encode())] * 30))

        phase("6., 7. long integers, duplicate names")
        text = json.dumps(duffing_spec(max_populations=1)).replace('"seed": 41', '"seed": ' + "7" * 5000)
        dup = duffing_spec(max_populations=1)
        dup["models"][1]["name"] = dup["models"][0]["name"]
        asyncio.run(at_once([body(text.encode()), upload(text, zeros_npz(10, "float64", {})),
                             body(json.dumps(dup).encode())]))

        phase("9. headers, dropped streams, concurrent results of a large job")
        statuses[httpx.get(f"{service.url}/health", headers={"X-Pad": "a" * 100_000}, timeout=30).status_code] += 1
        big = duffing_spec(max_populations=10, particles=20_000)
        big["sampler"]["batch_size"] = 1000
        job_id = httpx.post(f"{service.url}/jobs", json=big, headers=AUTH, timeout=60).json()["id"]
        for _ in range(20):
            with httpx.stream("GET", f"{service.url}/jobs/{job_id}/events", headers=AUTH, timeout=600) as r:
                for line in r.iter_lines():
                    if line.startswith("event: started") or line.startswith("event: population"):
                        break
        while httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()["status"] not in (
                "finished", "failed", "cancelled"):
            time.sleep(1)
        asyncio.run(at_once([lambda http: http.get(f"/jobs/{job_id}/result")] * 20))

        phase("beyond the issue: two uploads of whole 2^25-sample records at once (no fit window: the largest "
              "a job may hold)")
        asyncio.run(at_once([upload(whole, zeros_npz(2**25, "float64", head))] * 2))
        phase("")
    finally:
        done.set()
        poller.join(timeout=60)
        errors = close_and_count(service, cluster, statuses, start)
    print(f"/health: {len(health)} probes, slowest {max(health):.3f} s, p99 {np.percentile(health, 99):.3f} s")
    print("peak RSS by phase (MB): the service process, the process that parses submissions")
    for name, main_mb, child_mb in peaks:
        print(f"  {main_mb:6.0f} {child_mb:6.0f}  {name}")
    issue = [p for p in peaks if not p[0].startswith("beyond")]
    print(f"peak RSS through the issue's suite: service {max(p[1] for p in issue):.0f} MB, parser "
          f"{max(p[2] for p in issue):.0f} MB")
    print(f"errors in the service's log: {errors or 'none'}")


# ---------------------------------------------------------------------------- issue Z
def trailing_npz(head: dict[str, np.ndarray], name: str, trailing: int, compression: int) -> bytes:
    """An .npz of the arrays ``head`` (each member with an honest npy header), the member
    ``name`` followed by ``trailing`` undeclared zero bytes, every member compressed with
    ``compression`` (a zip method), streamed: the zeros are never held whole."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=compression) as zf:
        for key, array in head.items():
            with zf.open(f"{key}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, array)
                zeros, left = bytes(16 << 20), trailing if key == name else 0
                while left:
                    f.write(zeros[: min(left, len(zeros))])
                    left -= min(left, len(zeros))
    return buffer.getvalue()


class Watch:
    """/health polled every 0.05 s from a thread; ``slowest()`` since the last ``reset()``."""

    def __init__(self, url: str):
        self.url, self.times, self.done = url, [0.0], threading.Event()
        self.at: list[tuple[float, float]] = []  # (when it answered, seconds it took)
        self.thread = threading.Thread(target=self._poll, daemon=True)
        self.thread.start()

    def _poll(self) -> None:
        with httpx.Client(timeout=120, limits=httpx.Limits(max_keepalive_connections=0)) as client:
            while not self.done.is_set():
                start = time.perf_counter()
                try:
                    client.get(f"{self.url}/health")
                except httpx.HTTPError:
                    pass
                self.times.append(time.perf_counter() - start)
                self.at.append((time.time(), self.times[-1]))
                time.sleep(0.05)

    def reset(self) -> None:
        self.times = [0.0]

    def slowest(self) -> float:
        return max(self.times)

    def slowest_between(self, start: float, end: float) -> float:
        """The slowest answer that came between ``start`` and ``end`` (time.time())."""
        return max((took for at, took in self.at if start <= at <= end), default=0.0)

    def close(self) -> None:
        self.done.set()
        self.thread.join(timeout=130)


def _archives(statuses: collections.Counter, service: Service, watch: Watch) -> list[str]:
    """Z.2: 1,000 samples with an honest header and 1 GiB of undeclared zeros after them,
    bzip2, LZMA and deflate: each upload's answer, time, the service's peak memory growth and
    /health's slowest answer meanwhile."""
    folder = ROOT / "examples" / "duffing_41"
    head = {"force": np.load(folder / "force.npy"), "x": np.load(folder / "displacement.npy")}
    spec = duffing_spec(max_populations=1, particles=200)
    spec["data"].update(input="npz:force", observed="npz:x")
    lines = []
    for label, method in (("bzip2", zipfile.ZIP_BZIP2), ("lzma", zipfile.ZIP_LZMA), ("deflate", zipfile.ZIP_DEFLATED)):
        data = trailing_npz(head, "x", 1 << 30, method)
        pid = service.proc.pid  # type: ignore[union-attr]
        reset_peak(pid)
        before = service.rss_mb()
        watch.reset()
        start = time.perf_counter()
        r = httpx.post(f"{service.url}/jobs/upload", headers=AUTH, timeout=600,
                       files={"spec": ("spec.json", json.dumps(spec).encode()), "data": ("x.npz", data)})
        took = time.perf_counter() - start
        statuses[r.status_code] += 1
        field = r.json()["detail"][0]["field"] if r.status_code == 422 else ""
        lines.append(f"{label:8s} {len(data) / 1024:9.0f} KB upload: {r.status_code} {field} in {took:.2f} s, RSS "
                     f"{before:.0f} -> peak {peak_mb(pid):.0f} MB, /health slowest {watch.slowest():.3f} s")
        if r.status_code == 201:
            httpx.delete(f"{service.url}/jobs/{r.json()['id']}", headers=AUTH, timeout=60)
    return lines


def _bad_inputs() -> list[tuple[str, bytes, str]]:
    """Z.3, Z.4, Z.8: (label, JSON body or YAML spec, "json" | "yaml") of each input that
    answered 500 or was accepted to no purpose."""
    def spec_with(change) -> dict:
        spec = duffing_spec(max_populations=1, particles=200)
        change(spec)
        return spec

    json_cases = {
        "noise_std 1e200": lambda s: s["data"].update(noise_std=1e200),
        "fs 1e-300": lambda s: s["data"].update(fs=1e-300), "fs 1e-12": lambda s: s["data"].update(fs=1e-12),
        "fs 1e12": lambda s: s["data"].update(fs=1e12),
        "epsilon_initial 1e-300": lambda s: s["sampler"].update(epsilon_initial=1e-300),
        "constant record": lambda s: s["data"].update(observed=[0.3] * 1000),
        "record x 1e99": lambda s: s["data"].update(observed=[v * 1e99 for v in s["data"]["observed"]]),
        "input x 2^62": lambda s: s["data"].update(input=[v * 2.0**62 for v in s["data"]["input"]]),
        "2-sample record": lambda s: s["data"].update(input=s["data"]["input"][:2], observed=s["data"]["observed"][:2],
                                                      fit=None, test=None),
        "models Cubic / cubic": lambda s: s["models"][1].update(name=s["models"][0]["name"].upper()),
        "name with U+202E": lambda s: s.update(name="job\u202egnp.exe"),
        "name with U+200B": lambda s: s.update(name="paper\u200b-4.1-duffing"),
        "name with a trailing space": lambda s: s.update(name="paper-4.1-duffing "),
        "name alike an existing one": lambda s: s.update(name="Paper-4.1-Duffing"),
    }
    out = [(label, json.dumps(spec_with(change)).encode(), "json") for label, change in json_cases.items()]
    text = json.dumps(spec_with(lambda s: s["data"].update(input="npz:force", observed="npz:x")))
    for label, number in (("YAML 0x integer", "0x" + "f" * 5000), ("YAML 5,000-digit integer", "7" * 5000)):
        out.append((label, text.replace('"seed": 41', f'"seed": {number}').encode(), "yaml"))
    return out


def _inputs(statuses: collections.Counter, service: Service) -> list[str]:
    folder = ROOT / "examples" / "duffing_41"
    npz = io.BytesIO()
    np.savez(npz, force=np.load(folder / "force.npy"), x=np.load(folder / "displacement.npy"))
    header = b"{'descr': '<f8', 'fortran_order': False, 'shape': (1000,".ljust(117) + b"\n"  # cut short
    cut = io.BytesIO()
    with zipfile.ZipFile(cut, "w") as zf:
        for key in ("force", "x"):
            zf.writestr(f"{key}.npy", b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header)
    # the baseline job, so that a name alike it exists
    statuses[httpx.post(f"{service.url}/jobs", json=duffing_spec(max_populations=1, particles=200), headers=AUTH,
                        timeout=120).status_code] += 1
    lines = []
    for label, body, kind in [*_bad_inputs(), ("npy header cut short", b"", "cut")]:
        if kind == "json":
            r = httpx.post(f"{service.url}/jobs", content=body, timeout=120,
                           headers={**AUTH, "Content-Type": "application/json"})
        else:
            spec = body if kind == "yaml" else json.dumps(
                {**duffing_spec(max_populations=1), "data": {**duffing_spec()["data"], "input": "npz:force",
                                                             "observed": "npz:x"}}).encode()
            data = npz.getvalue() if kind == "yaml" else cut.getvalue()
            r = httpx.post(f"{service.url}/jobs/upload", headers=AUTH, timeout=120,
                           files={"spec": ("spec.yaml", spec), "data": ("x.npz", data)})
        statuses[r.status_code] += 1
        field = r.json()["detail"][0]["field"] if r.status_code == 422 else ""
        lines.append(f"{label:28s} {r.status_code} {field}")
        if r.status_code == 201:
            httpx.delete(f"{service.url}/jobs/{r.json()['id']}", headers=AUTH, timeout=60)
    return lines


def _slow_bodies(statuses: collections.Counter, service: Service) -> str:
    """Z.7: four connections sending a body a byte a second, then a submission: its wait."""
    def drip(done: threading.Event) -> None:
        with socket.create_connection(("127.0.0.1", service.port), timeout=120) as s:
            s.sendall(b"POST /jobs HTTP/1.1\r\nHost: x\r\nAuthorization: " + AUTH["Authorization"].encode()
                      + b"\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n{")
            try:
                while not done.is_set() and not select.select([s], [], [], 1.0)[0]:
                    s.sendall(b" ")
            except OSError:
                pass

    done = threading.Event()
    drips = [threading.Thread(target=drip, args=(done,), daemon=True) for _ in range(4)]
    for t in drips:
        t.start()
    time.sleep(1.0)  # the four hold the slots
    start = time.perf_counter()
    r = httpx.post(f"{service.url}/jobs", json=duffing_spec(max_populations=1, particles=200), headers=AUTH, timeout=600)
    took = time.perf_counter() - start
    statuses[r.status_code] += 1
    done.set()
    for t in drips:
        t.join(timeout=60)
    if r.status_code == 201:
        httpx.delete(f"{service.url}/jobs/{r.json()['id']}", headers=AUTH, timeout=60)
    return f"a submission behind four 1-byte/s bodies: {r.status_code} after {took:.1f} s"


def _purges(statuses: collections.Counter, service: Service, rounds: int = 10) -> str:
    """Z.8: two purges at once of an ended job, ``rounds`` times: the answers."""
    pairs: collections.Counter = collections.Counter()
    for _ in range(rounds):
        job_id = httpx.post(f"{service.url}/jobs", json=duffing_spec(max_populations=1, particles=200), headers=AUTH,
                            timeout=120).json()["id"]
        while httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()["status"] not in (
                "finished", "failed", "cancelled"):
            time.sleep(0.2)

        async def both(job: str) -> list[int]:
            async with httpx.AsyncClient(base_url=service.url, headers=AUTH, timeout=60) as http:
                answers = await asyncio.gather(*(http.delete(f"/jobs/{job}", params={"purge": "true"}) for _ in range(2)))
            return sorted(a.status_code for a in answers)

        codes = asyncio.run(both(job_id))
        statuses.update(codes)
        pairs[tuple(codes)] += 1
    return "two purges at once: " + ", ".join(f"{n} x {list(c)}" for c, n in sorted(pairs.items()))


TERMINAL_EVENTS = (b"event: finished", b"event: failed", b"event: cancelled")


async def _one_stream(port: int, path: str, token: str, connected=lambda: None) -> tuple[bool, int]:
    """One raw event stream (a socket, no client library: 500 of them cost the client little
    CPU): whether it got the job's terminal event, and the bytes read. ``connected()`` is
    called once its answer's head has come."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: x\r\nAuthorization: {token}\r\n\r\n".encode())
    await writer.drain()
    got, tail, head = 0, b"", False
    try:
        while chunk := await reader.read(65536):
            got += len(chunk)
            tail = (tail + chunk)[-4096:]
            if not head and b"\r\n\r\n" in tail:
                head = True
                connected()
            if any(t in tail for t in TERMINAL_EVENTS):
                return True, got
        return False, got
    finally:
        writer.close()


def stream_clients(port: int, path: str, token: str, n: int, ready, results) -> None:
    """``n`` event streams at once (in a process of their own); sets ``ready`` once every
    stream is open, then puts how many got the terminal event and the bytes read by each
    on ``results``."""
    count = [0]

    def connected() -> None:
        count[0] += 1
        if count[0] == n:
            ready.set()

    async def all_of_them() -> list:
        return await asyncio.gather(*(_one_stream(port, path, token, connected) for _ in range(n)),
                                    return_exceptions=True)

    out = asyncio.run(all_of_them())
    results.put((sum(1 for o in out if isinstance(o, tuple) and o[0]),
                 [o[1] if isinstance(o, tuple) else -1 for o in out]))


def _job_times(service: Service, job_id: str) -> tuple[str, float, float, int]:
    """(status, time of its start event, of its end event, populations) of an ended job."""
    events = [json.loads(line) for line in (service.job_dir(job_id) / "events.jsonl").read_text().splitlines()]
    start = next(e["time"] for e in events if e["event"] == "started")
    return events[-1]["event"], start, events[-1]["time"], sum(e["event"] == "population" for e in events)


def _streams(statuses: collections.Counter, service: Service, watch: Watch, counts=(0, 0, 100, 500)) -> list[str]:
    """Z.1: ``n`` event streams on one job, opened while it waits behind another (the
    service runs one job at a time); once all are open the other is cancelled and the job
    runs (~5 s alone): /health's slowest answer while it runs, its time from start to end,
    and how many streams got its end event. The first run (no streams) warms the workers."""
    import multiprocessing

    spec = duffing_spec(max_populations=100, particles=2000, noise_floor=False)
    blocker = duffing_spec(max_populations=100_000, particles=200, noise_floor=False)
    lines = []
    ctx = multiprocessing.get_context("spawn")

    def submit(raw: dict) -> str:
        r = httpx.post(f"{service.url}/jobs", json=raw, headers=AUTH, timeout=120)
        statuses[r.status_code] += 1
        return r.json()["id"]

    for n in counts:
        first, job_id = submit(blocker), submit(spec)
        ready, results = ctx.Event(), ctx.Queue()
        clients = ctx.Process(target=stream_clients, args=(service.port, f"/jobs/{job_id}/events",
                                                           AUTH["Authorization"], n, ready, results))
        if n:
            clients.start()
            if not ready.wait(300):
                lines.append(f"{n:4d} streams: not all open after 300 s")
        statuses[httpx.delete(f"{service.url}/jobs/{first}", headers=AUTH, timeout=120).status_code] += 1
        watch.reset()
        while httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH, timeout=120).json()["status"] not in (
                "finished", "failed", "cancelled"):
            time.sleep(0.2)
        slowest = watch.slowest()
        got, sizes = results.get(timeout=300) if n else (0, [])
        if n:
            clients.join(timeout=60)
        status, began, ended, pops = _job_times(service, job_id)
        lines.append(f"{n:4d} streams: job {status} ({pops} populations) in {ended - began:.1f} s, "
                     f"{got}/{n} streams got its end ({min(sizes, default=0)}-{max(sizes, default=0)} bytes), "
                     f"/health slowest {slowest:.3f} s (while it ran {watch.slowest_between(began, ended):.3f} s)")
    return lines


def _fill(path: Path, leave_bytes: int) -> Path:
    """A file in ``path`` that leaves about ``leave_bytes`` free on its disk."""
    filler = path / "filler"
    free = shutil.disk_usage(path).free
    with filler.open("ab") as f:
        f.write(bytes(max(0, free - leave_bytes)))
    return filler


def _disk(statuses: collections.Counter, tmp: Path, cluster: StockCluster, size_mb: int = 12) -> list[str]:
    """Z.6 on a tmpfs of ``size_mb`` MB (mounted here: root) as the job store: a submission
    with a few KB free; then a job whose store outgrows the disk once a filler took half of
    it: it is requeued and waits, the filler goes, it resumes and ends; its populations
    against the same job's on a disk with room."""
    disk = tmp / "tmpfs"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(disk)], check=True)
    service = Service(disk / "jobs", cluster.address, env={"ABCNS_DISK_RESERVE_MB": "0"})
    lines = []
    try:
        filler = _fill(disk, 8 << 10)
        r = httpx.post(f"{service.url}/jobs", json=duffing_spec(max_populations=40, particles=5000, noise_floor=False),
                       headers=AUTH, timeout=120)
        statuses[r.status_code] += 1
        lines.append(f"8 KB free: {r.status_code} {r.json().get('detail', '')}")
        filler.unlink()
        spec = duffing_spec(max_populations=40, particles=5000, noise_floor=False)
        r = httpx.post(f"{service.url}/jobs", json=spec, headers=AUTH, timeout=120)
        statuses[r.status_code] += 1
        job_id = r.json()["id"]
        filler = _fill(disk, (size_mb << 20) // 2)
        start = time.monotonic()
        wait_until(lambda: b"requeued" in (service.job_dir(job_id) / "events.jsonl").read_bytes(), 300,
                   "the job to find the disk full")
        stored = Store.open(service.job_dir(job_id) / "store.zarr").n_populations
        lines.append(f"the disk full after {time.monotonic() - start:.1f} s at {stored} populations; "
                     f"status {httpx.get(f'{service.url}/jobs/{job_id}', headers=AUTH).json()['status']}")
        time.sleep(3)  # it waits for room
        waiting = httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()["status"]
        filler.unlink()
        wait_until(lambda: httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()["status"] in
                   ("finished", "failed", "cancelled"), 600, "the job to end")
        info = httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()
        left = [p.name for p in service.job_dir(job_id).rglob("*") if p.suffix in (".tmp", ".partial")]
        same = _same(service.job_dir(job_id) / "store.zarr", _reference(tmp, cluster, spec))
        lines.append(f"3 s later: {waiting}; room again: {info['status']} "
                     f"({Store.open(service.job_dir(job_id) / 'store.zarr').n_populations} populations), "
                     f"temporary files left: {left or 'none'}, populations identical to an uninterrupted run: {same}")
    finally:
        service.close()
        subprocess.run(["umount", "--lazy", str(disk)], check=False)
    return lines


def _reference(tmp: Path, cluster: StockCluster, spec: dict) -> Path:
    """The store of ``spec`` run by a service on a disk with room (the same cluster)."""
    service = Service(tmp / "reference", cluster.address)
    try:
        job_id = httpx.post(f"{service.url}/jobs", json=spec, headers=AUTH, timeout=120).json()["id"]
        wait_until(lambda: httpx.get(f"{service.url}/jobs/{job_id}", headers=AUTH).json()["status"] in
                   ("finished", "failed", "cancelled"), 600, "the reference job to end")
        return service.job_dir(job_id) / "store.zarr"
    finally:
        service.close()


def _same(a: Path, b: Path) -> str:
    """"yes", or the first population and array where two stores differ."""
    sa, sb = Store.open(a), Store.open(b)
    if sa.n_populations != sb.n_populations:
        return f"no: {sa.n_populations} and {sb.n_populations} populations"
    for p, q in zip(sa.populations(), sb.populations()):
        for k in ("models", "theta", "distances", "weights"):
            if not np.array_equal(getattr(p, k), getattr(q, k), equal_nan=k != "models"):
                return f"no: population {p.t} differs in {k}"
    return "yes"


def main_disk() -> None:
    """Z.6: a full disk (``--disk``; mounts a tmpfs: root)."""
    tmp = Path(tempfile.mkdtemp())
    cluster = StockCluster(tmp / "dask")
    statuses: collections.Counter = collections.Counter()
    try:
        print("Z.6 a full disk", flush=True)
        for line in _disk(statuses, tmp, cluster):
            print(line, flush=True)
    finally:
        cluster.close()
    print("answers: " + ", ".join(f"{n} x {s}" for s, n in sorted(statuses.items())))


def _on_service(title: str, attacks) -> None:
    """Run ``attacks(statuses, service, watch)`` (its lines printed) on `abcns serve` with its
    default settings on a stock cluster; then the answers by status and the log's errors."""
    tmp = Path(tempfile.mkdtemp())
    cluster = StockCluster(tmp / "dask")
    service = Service(tmp / "jobs", cluster.address)
    statuses: collections.Counter = collections.Counter()
    watch = Watch(service.url)
    start = time.monotonic()
    try:
        print(title, flush=True)
        for line in attacks(statuses, service, watch):
            print(line, flush=True)
    finally:
        watch.close()
        errors = close_and_count(service, cluster, statuses, start)
    print(f"errors in the service's log: {errors[:2000] or 'none'}")


def main_streams() -> None:
    """Z.1: many event streams on one running job (``--streams``)."""
    _on_service("Z.1 event streams on one running job", _streams)


def _issue_z(statuses: collections.Counter, service, watch):
    """Issue Z's attacks 2, 3, 4, 7 and 8, their lines as they end."""
    yield "Z.2 archives: 1,000 samples, then 1 GiB of undeclared zeros"
    yield "\n".join(_archives(statuses, service, watch))
    yield "Z.3, Z.4, Z.8 inputs"
    yield "\n".join(_inputs(statuses, service))
    yield "Z.7 slow bodies"
    yield _slow_bodies(statuses, service)
    yield "Z.8 purges"
    yield _purges(statuses, service)


def main_z() -> None:
    """Issue Z's attacks (2, 3, 4, 7, 8) on `abcns serve` with its default settings."""
    _on_service("issue Z", _issue_z)


if __name__ == "__main__":
    import sys

    if "--streams" in sys.argv[1:]:
        main_streams()
    elif "--disk" in sys.argv[1:]:
        main_disk()
    else:
        main_z() if "--issue-z" in sys.argv[1:] else main()
