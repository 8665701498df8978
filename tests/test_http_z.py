"""The service holds, round three (issue Z): odd archives, inputs that answered 500,
specs that cannot mean anything, slow bodies and names that look alike. Each test names the
finding it covers; each runs on real processes (`abcns serve`, a stock `dask scheduler`
and workers), except Z.8's purge race, which is driven on the route itself (two purges at
once cannot be ordered from outside)."""

from __future__ import annotations

import io
import json
import select
import socket
import struct
import threading
import zipfile

import httpx
import numpy as np
import pytest
import yaml
from fastapi import HTTPException

from benchmarks.harness import AUTH, ROOT, TOKEN, Service, duffing_spec

pytestmark = pytest.mark.http
FOLDER = ROOT / "examples" / "duffing_41"


def post(service: Service, spec: dict, path: str = "/jobs") -> httpx.Response:
    return httpx.post(f"{service.url}{path}", content=json.dumps(spec), timeout=120,
                      headers={**AUTH, "Content-Type": "application/json"})


def upload(service: Service, spec: dict | str, npz: bytes, name: str = "spec.json") -> httpx.Response:
    text = spec if isinstance(spec, str) else json.dumps(spec)
    return httpx.post(f"{service.url}/jobs/upload", headers=AUTH, timeout=120,
                      files={"spec": (name, text.encode()), "data": ("x.npz", npz)})


def refused(r: httpx.Response, field: str, words: str = "") -> None:
    assert r.status_code == 422, (field, r.status_code, r.text[:300])
    detail = r.json()["detail"][0]
    assert detail["field"] == field and words in detail["msg"], (field, detail)


def jobs(service: Service) -> list[str]:
    return [j["id"] for j in httpx.get(f"{service.url}/jobs", headers=AUTH, timeout=60).json()]


def npz(members: dict[str, bytes], compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=compression) as zf:
        for name, raw in members.items():
            zf.writestr(f"{name}.npy", raw)
    return buffer.getvalue()


def npy(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.lib.format.write_array(out, array)
    return out.getvalue()


def upload_spec() -> dict:
    spec = duffing_spec(max_populations=1, particles=200)
    spec["data"].update(input="npz:force", observed="npz:x")
    return spec


# ---------------------------------------------------------------------------- Z.2
def test_only_stored_or_deflated_members_of_their_declared_size_are_read(service):
    """Z.2: an .npz member compressed with bzip2 or LZMA (whose reader decompresses a block
    whole: 17 KB became 2 GB) is refused naming the field, so is a member that holds more
    (or less) than its npy header declares, whatever its compression: refused from the zip's
    directory, never decompressed. numpy's own savez and savez_compressed pass."""
    force, x = npy(np.load(FOLDER / "force.npy")), npy(np.load(FOLDER / "displacement.npy"))
    spec = upload_spec()
    for method in (zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA):
        refused(upload(service, spec, npz({"force": force, "x": x}, method)), "data.input", f"zip method {method}")
    trailing = x + bytes(16 << 20)  # an honest header, then 16 MiB it does not declare
    for method in (zipfile.ZIP_DEFLATED, zipfile.ZIP_STORED, zipfile.ZIP_BZIP2):
        members = {"force": force, "x": trailing}
        r = upload(service, spec, npz(members, method))
        if method == zipfile.ZIP_BZIP2:  # refused at the first array read, before its header is
            refused(r, "data.input", "zip method 12")
        else:
            refused(r, "data.observed", "header declares")
    refused(upload(service, spec, npz({"force": force, "x": x[:-80]})), "data.observed", "header declares")
    for method in (zipfile.ZIP_DEFLATED, zipfile.ZIP_STORED):
        r = upload(service, spec, npz({"force": force, "x": x}, method))
        assert r.status_code == 201, r.text
        httpx.delete(f"{service.url}/jobs/{r.json()['id']}", headers=AUTH, timeout=60)


# ---------------------------------------------------------------------------- Z.3
def test_inputs_that_answered_500_answer_422_naming_the_field(service):
    """Z.3: a noise_std whose square overflows, a YAML 0x or 0b integer too long to print
    (and one of 5,000 decimal digits, Z.8, named by its field, not `spec`), and npy headers
    cut short or with a negative dimension: each a 422 naming the field."""
    spec = duffing_spec(max_populations=1)
    spec["data"]["noise_std"] = 1e200
    refused(post(service, spec), "data.noise_std")
    text = yaml.safe_dump(upload_spec())
    data = npz({"force": npy(np.load(FOLDER / "force.npy")), "x": npy(np.load(FOLDER / "displacement.npy"))})
    for number in ("0x" + "f" * 5000, "-0x" + "f" * 4000, "0b" + "1" * 20_000, "7" * 5000, "1_" * 4400):
        r = upload(service, text.replace("seed: 41", f"seed: {number}"), data, "spec.yaml")
        refused(r, "seed", "digits")
    for header in (b"{'descr': '<f8', 'fortran_order': False, 'shape': (1000,",
                   b"{'descr': '<f8', 'fortran_order': False, 'shape': (-1,), }"):
        header = header.ljust(117) + b"\n"
        cut = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header
        r = upload(service, upload_spec(), npz({"force": npy(np.load(FOLDER / "force.npy")), "x": cut}))
        refused(r, "data.observed", "not a readable .npy")


# ---------------------------------------------------------------------------- Z.4
MEANINGLESS = (
    (lambda s: s["data"].update(fs=1e-300), "data.fs", "Nyquist"),
    (lambda s: s["data"].update(fs=1e-12), "data.fs", "Nyquist"),
    (lambda s: s["data"].update(fs=1e12), "data.fs", "one period"),
    (lambda s: s["sampler"].update(epsilon_initial=1e-300), "sampler.epsilon_initial", "below"),
    (lambda s: s["data"].update(noise_std=0.0025) or s["sampler"].update(epsilon_initial=1e-4),
     "sampler.epsilon_initial", "noise_std"),
    (lambda s: s["data"].update(observed=[0.3] * 1000), "data.observed", "constant"),
    (lambda s: s["data"].update(observed=[v * 1e99 for v in s["data"]["observed"]]), "data.observed", "units"),
    (lambda s: s["data"].update(input=[v * 2.0**62 for v in s["data"]["input"]]), "data.input", "units"),
    (lambda s: s["data"].update(input=[0.0] * 1000), "data.input", "nonzero"),
    (lambda s: s["data"].update(noise_std=1.0), "data.noise_std", "exceeds"),
    (lambda s: s["data"].update(input=s["data"]["input"][:2], observed=s["data"]["observed"][:2], fit=None, test=None),
     "data.observed", "at least 20"),
    (lambda s: s["data"].update(fit=[0, 10], test=None), "data.fit", "at least 20"),
    (lambda s: s["sampler"].update(epsilon_initial=None, pilot_size=10**12), "sampler.pilot_size", "limit"),
)


def test_specs_that_cannot_mean_anything_are_refused(service):
    """Z.4: each of these was accepted (201) and held the running slot for 14-47 s of
    simulations that ended `nothing_accepted`: a sampling rate that resolves no natural
    frequency the priors allow, or a window shorter than one period of the fastest; a first
    tolerance below what a simulation reaches; a constant record, one of no measured scale,
    an input of 2^62 or none; a noise larger than the record; two samples; a pilot of 10^12
    simulations. Each is a 422 naming the field, and nothing is queued."""
    before = jobs(service)
    for change, field, words in MEANINGLESS:
        spec = duffing_spec(max_populations=1)
        change(spec)
        refused(post(service, spec), field, words)
    assert jobs(service) == before
    spec = duffing_spec(max_populations=1, particles=200)
    spec["data"]["noise_std"] = 0.0025  # the record's 1 % noise stated, the default first tolerance
    r = post(service, spec)
    assert r.status_code == 201, r.text
    httpx.delete(f"{service.url}/jobs/{r.json()['id']}", headers=AUTH, timeout=60)


# ---------------------------------------------------------------------------- Z.7
def test_slow_bodies_cannot_hold_the_submission_slots(cluster, tmp_path):
    """Z.7: four connections that send a body a byte at a time (with a 600 s body deadline,
    they held both submission slots for it) get 408 once their grace is over, and a
    submission sent meanwhile is answered (201); submissions that wait for the one slot with
    their bodies unread (ABCNS_MAX_SUBMISSIONS=1: uvicorn stops reading them) are not
    counted slow."""
    service = Service(tmp_path / "jobs", cluster.address, env={"ABCNS_BODY_TIMEOUT_S": "600",
                                                                "ABCNS_MAX_SUBMISSIONS": "1"})
    answers: list[bytes] = []
    done = threading.Event()

    def drip() -> None:
        with socket.create_connection(("127.0.0.1", service.port), timeout=120) as s:
            s.sendall(b"POST /jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " + TOKEN.encode()
                      + b"\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n{")
            try:
                while not done.is_set() and not select.select([s], [], [], 0.5)[0]:  # until the server answers
                    s.sendall(b" ")
            except OSError:  # closed by the server
                pass
            out = b""
            try:
                while chunk := s.recv(4096):
                    out += chunk
            except OSError:
                pass
            answers.append(out)

    drips = [threading.Thread(target=drip, daemon=True) for _ in range(4)]
    try:
        for t in drips:
            t.start()
        spec = duffing_spec(max_populations=1, particles=200)
        spec["data"]["input"] = np.tile(spec["data"]["input"], 200).tolist()  # 200,000 samples: ~4 MB
        spec["data"]["observed"] = np.tile(spec["data"]["observed"], 200).tolist()
        body = json.dumps(spec).encode()

        def submit(out: list) -> None:
            out.append(httpx.post(f"{service.url}/jobs", content=body, timeout=90,
                                  headers={**AUTH, "Content-Type": "application/json"}))

        results: list[httpx.Response] = []
        submits = [threading.Thread(target=submit, args=(results,)) for _ in range(3)]
        for t in submits:
            t.start()
        for t in submits:
            t.join(timeout=120)
        assert [r.status_code for r in results] == [201] * 3, [r.text[:200] for r in results]
        for t in drips:
            t.join(timeout=60)
        assert len(answers) == 4 and all(a.startswith(b"HTTP/1.1 408") for a in answers), answers
        assert b"slower than 8192 bytes/s" in answers[0]
    finally:
        done.set()
        service.close()


# ---------------------------------------------------------------------------- Z.8
def test_the_second_of_two_purges_answers_404():
    """Z.8: a purge whose job another purge removed meanwhile (the manager's purge says
    False and the job is gone) answers 404, not 409 "has not ended"."""
    from service.http.api import cancel_or_purge

    class Gone:
        id, status = "a" * 32, "finished"

    class Manager:
        def purge(self, job_id: str) -> bool:
            return False

        def get(self, job_id: str) -> None:
            return None

    with pytest.raises(HTTPException) as err:
        cancel_or_purge(Gone(), Manager(), purge=True)  # type: ignore[arg-type]
    assert err.value.status_code == 404


def test_names_that_look_like_another_are_refused(service):
    """Z.8: a model name that differs from another's only by case or width, a name with
    surrounding space, a bidi override, a zero-width space or a byte-order mark, and a job
    name that differs from an existing job's only by case or trailing space: each a 422
    naming the field. The same name again is fine."""
    def named(job: str | None = None, first: str = "cubic", second: str = "cubic-quintic") -> dict:
        spec = duffing_spec(max_populations=1)
        spec["models"][0]["name"], spec["models"][1]["name"] = first, second
        if job is not None:
            spec["name"] = job
        return spec

    refused(post(service, named(second="Cubic")), "models[1].name", "only by case")
    refused(post(service, named(second="\uff43\uff55\uff42\uff49\uff43")), "models[1].name", "only by case")
    for name in ("cubic ", " cubic", "cu\u202ebic", "cu\u200bbic", "\ufeffcubic", "cu\u2028bic"):
        refused(post(service, named(first=name)), "models[0].name")
        refused(post(service, named(job=name)), "name")
    first = post(service, named(job="Z-names"))
    assert first.status_code == 201, first.text
    for alike in ("z-names", "Z-NAMES", "\uff3a-names"):
        refused(post(service, named(job=alike)), "name", first.json()["id"])
    again = post(service, named(job="Z-names"))
    assert again.status_code == 201, again.text
    for r in (first, again):
        httpx.delete(f"{service.url}/jobs/{r.json()['id']}", headers=AUTH, timeout=60)


def test_the_parsing_child_ends_with_a_service_killed_by_sigkill(cluster, tmp_path):
    """Z.8: `abcns serve` killed with SIGKILL (its process alone, not its group): the child
    process that parses submissions (~150 MB) and multiprocessing's resource tracker end
    with it, instead of waiting on their pipes for ever."""
    import os
    import signal

    import psutil

    from benchmarks.harness import wait_until

    service = Service(tmp_path / "jobs", cluster.address)
    children: list[psutil.Process] = []
    try:
        proc = psutil.Process(service.proc.pid)  # type: ignore[union-attr]
        r = post(service, {"name": "x"})  # a submission: the child has answered once
        assert r.status_code == 422
        children = proc.children(recursive=True)
        assert len(children) >= 2, children  # the parsing child and the resource tracker

        def alive(p: psutil.Process) -> bool:
            try:
                return p.is_running() and p.status() != psutil.STATUS_ZOMBIE
            except psutil.NoSuchProcess:
                return False

        os.kill(proc.pid, signal.SIGKILL)
        service.proc.wait()  # type: ignore[union-attr]
        wait_until(lambda: not any(alive(c) for c in children), 60, f"{[c.name() for c in children]} to end")
    finally:
        for c in children:  # (the code before this fix left them)
            try:
                c.kill()
            except psutil.NoSuchProcess:
                pass
        service.close()
