"""A submitted job spec, from bytes to a validated :class:`JobSpec` and its arrays, off the
event loop.

Parsing and validating a body is CPU work, and much of it is one C call that holds the GIL
throughout (``json.loads`` of 30 MB of numbers: ~1.5 s; pydantic's validation of a long
list): in a thread it would still stall the event loop, so ``/health``, every event stream
and the signals would wait. It runs in a child process instead (:class:`Intake`: one
spawned process, started with the service), and only a bounded number of
submissions are read and handled at once (``ABCNS_MAX_SUBMISSIONS``); the others wait for
a slot without holding their body in memory (uvicorn stops reading a body nobody reads).

In the child, :func:`spec_of` checks a body in this order, every refusal a 4xx naming the
field (``detail[i].field``):

1. its size before anything is parsed (:func:`scan`): at most ``max_values`` JSON values
   (numbers, strings, lists, objects) and ``MAX_CONTAINERS`` lists and objects, bounded
   from the raw bytes (413 naming ``body`` or ``spec``); a YAML spec (an upload's ``spec``
   part) is at most ``MAX_YAML_BYTES`` (its data go in the ``.npz``);
2. JSON (400) or YAML (422): a number of more digits than Python converts or prints (a
   YAML 0x integer included) is found by name (422 naming its field), not as a server error;
3. one iterative walk (:func:`check_input`), which stops past ``MAX_DEPTH`` levels or
   ``max_values`` values (413; a YAML alias is counted each time it is used): every string
   Unicode text, every number finite, every key text, only JSON's kinds of values (YAML's
   dates, sets and binaries are refused), and the names short text without hidden
   characters or surrounding space, no two models' names alike but for case (:func:`check_names`);
4. the schema (422, pydantic's errors with ``field``, the offending value as text).

The inline data come back as float arrays, not as lists (the spec names them
``data.npz:input`` / ``data.npz:observed``, where the job manager stores them).
"""

from __future__ import annotations

import asyncio
import ctypes
import json
import math
import multiprocessing
import os
import re
import signal
import sys
import unicodedata
from concurrent.futures import BrokenExecutor, ProcessPoolExecutor
from contextlib import asynccontextmanager
from typing import Any

import numpy as np
import yaml
from pydantic import ValidationError

from service.http.jobs import DATA_FILE, clean_text
from service.http.schemas import NAME_MAX_CHARS
from service.spec import JobSpec, _field, branch_errors, spec_loc

MAX_DEPTH = 32  # nesting of a spec: the deepest field is 5 levels down (models[0].priors.k[1])
MAX_YAML_BYTES = 1 << 20  # a YAML spec refers to its data in the upload; 1 MiB of YAML parses in ~0.1 s
MAX_CONTAINERS = 100_000  # lists and objects in one body (a spec has a few dozen)
TEXT_MAX = 200  # characters of an offending value shown in a 422
INT_DIGITS = 4300  # Python's limit on converting a decimal string to int (sys.get_int_max_str_digits)
INT_BITS = 14_000  # an int of at most this many bits has at most 4,215 decimal digits: it prints


class Refused(Exception):
    """An answer other than 2xx: ``status`` and ``detail`` (a list of items naming the field,
    or a text). Picklable, so it crosses from the child process."""

    def __init__(self, status: int, detail: Any, headers: dict[str, str] | None = None):
        super().__init__(status, detail, headers)
        self.status, self.detail, self.headers = status, detail, headers


def problem(status: int, field: str, msg: str, kind: str, value: Any = None) -> Refused:
    """An error naming the field: ``detail[0].field`` (``sampler.particles``, ``models[0].name``)."""
    field = clean_text(field)  # a key may be what is wrong
    loc = ["body", *[p for p in re.split(r"[.\[\]]+", field) if p and field != "body"]]
    item = {"loc": loc, "field": field, "msg": msg, "type": kind}
    if value is not None:
        item["input"] = as_text(value)
    return Refused(status, [item])


def as_text(value: Any) -> str:
    """A value as a short text: NaN and Infinity included, long values cut."""
    if isinstance(value, str):
        text = value
    elif isinstance(value, int) and value.bit_length() > INT_BITS:  # str() of it fails
        text = f"(an integer of about {int(value.bit_length() * math.log10(2)) + 1:,} digits)"
    elif isinstance(value, float) and not math.isfinite(value):
        text = "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")
    elif isinstance(value, (list, dict)) and (len(value) > 20 or any(
            isinstance(v, (list, dict)) for v in (value.values() if isinstance(value, dict) else value))):
        text = f"a {'list' if isinstance(value, list) else 'mapping'} of {len(value)} items"  # never dumped whole
    else:
        try:
            text = json.dumps(value, default=str)
        except ValueError:  # NaN inside a container
            text = repr(value)
    text = clean_text(text)
    return text if len(text) <= TEXT_MAX else text[:TEXT_MAX] + f"... ({len(text)} characters)"


def validation_errors(errors: Any) -> list[dict]:
    """pydantic's errors with ``field`` (the dotted path) and the input as text."""
    out = []
    for e in branch_errors(list(errors)):  # a null inline: its sample, not the file-name branch
        loc = [p if isinstance(p, int | str) else str(p) for p in e.get("loc", ())]
        where = loc[:1] if loc and loc[0] in ("body", "query", "path", "header", "cookie") else []
        path = list(spec_loc(tuple(loc[len(where):])))  # sampler.alpha, not sampler.abc-ns.alpha
        loc = where + path
        item = {"loc": [clean_text(p) if isinstance(p, str) else p for p in loc],
                "field": clean_text(_field(tuple(path)) or (str(loc[0]) if loc else "")),
                "msg": clean_text(str(e.get("msg"))), "type": str(e.get("type"))}
        if "input" in e:
            item["input"] = as_text(e["input"])
        out.append(item)
    return out


# ---------------------------------------------------------------------------- 1. before parsing
def scan(body: bytes, field: str, max_values: int) -> None:
    """Refuse a JSON body that may hold more than ``max_values`` values or MAX_CONTAINERS
    lists and objects, from its bytes: a few C passes, before a single object is made. The
    counts (separators and brackets, those inside strings too) bound the values from above;
    no spec has many of them inside its strings. (The depth is the walk's to check: the
    parser itself stops at Python's recursion limit, ~1,000 levels, cheaply.)"""
    containers = body.count(b"[") + body.count(b"{")
    values = body.count(b",") + body.count(b":") + containers + 1  # "a": 1 is two values
    if containers > MAX_CONTAINERS or values > max_values:
        raise problem(413, field, f"holds up to {values:,} JSON values in up to {containers:,} lists and objects; the "
                                  f"limit is {max_values:,} values and {MAX_CONTAINERS:,} lists and objects (give large "
                                  "data as an .npz upload: POST /jobs/upload)", "too_large")


# ---------------------------------------------------------------------------- 2. parsing
class Digits(int):
    """A number of more digits than Python converts, in place of its value (its field is
    named by :func:`check_input`)."""


def _int(text: str) -> int:
    return int(text) if len(text.lstrip("-")) <= INT_DIGITS else Digits(len(text.lstrip("-")))


def parse_json(body: bytes, field: str) -> Any:
    """JSON text -> value; 400 for anything that is not UTF-8 JSON."""
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as err:
        raise Refused(400, [_parse_item(field, f"not UTF-8 ({err.reason} at byte {err.start})")]) from None
    try:
        try:
            return json.loads(text)
        except json.JSONDecodeError:
            raise
        except ValueError:  # an integer of more digits than Python converts: find it by name
            return json.loads(text, parse_int=_int)
    except json.JSONDecodeError as err:
        raise Refused(400, [_parse_item(field, f"not JSON: {err}")]) from None
    except RecursionError:
        raise problem(413, field, f"nests deeper than {MAX_DEPTH} levels", "too_deep") from None


def _yaml_int(loader: Any, node: Any) -> int:
    """YAML's integer (decimal, 0b, 0o, 0x, sexagesimal), or :class:`Digits` when it has more
    digits than Python converts or prints (a 0x integer converts at any length, and then
    fails in the message that shows it): its field is named by :func:`check_input`."""
    text = str(node.value).replace("_", "").lstrip("+-")
    if len(text) > INT_DIGITS:
        return Digits(len(text))
    value = yaml.constructor.SafeConstructor.construct_yaml_int(loader, node)
    if value.bit_length() > INT_BITS:
        return Digits(int(value.bit_length() * math.log10(2)) + 1)
    return value


class _YamlLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # type: ignore[misc]  # C or Python, chosen at import
    """The safe loader (C when built), its integers by :func:`_yaml_int`."""


_YamlLoader.add_constructor("tag:yaml.org,2002:int", _yaml_int)


def parse_yaml(text: bytes, field: str) -> Any:
    """A YAML spec (what `abcns run` reads) -> value; 422 naming ``field`` when it is not YAML."""
    if len(text) > MAX_YAML_BYTES:
        raise problem(413, field, f"a YAML spec is at most {MAX_YAML_BYTES:,} bytes, got {len(text):,} (give the data "
                                  "in the .npz: input: npz:KEY)", "too_large")
    try:
        return yaml.load(text, Loader=_YamlLoader)  # noqa: S506 - a safe loader (C or Python)
    except yaml.YAMLError as err:
        raise problem(422, field, f"neither JSON nor YAML: {str(err)[:TEXT_MAX]}", "yaml") from None
    except (RecursionError, ValueError, TypeError) as err:  # nesting, digits, an unhashable key
        raise problem(422, field, f"not a readable YAML spec: {type(err).__name__}: {str(err)[:TEXT_MAX]}",
                      "yaml") from None


def _parse_item(field: str, msg: str) -> dict:
    return {"loc": ["body"] if field == "body" else ["body", field], "field": field, "msg": msg, "type": "parse"}


# ---------------------------------------------------------------------------- 3. the walk
def _scalar(v: Any, path: tuple, key: Any, field: str) -> None:
    """One value that is not a list or a mapping, at ``path + (key,)`` (made only to name a
    refusal: a list of a million numbers makes no paths)."""
    if isinstance(v, str):
        try:
            v.encode("utf-8")
        except UnicodeEncodeError:
            raise problem(422, _field((*path, key)) or field, "not valid Unicode text (a lone surrogate)", "text",
                          v) from None
    elif isinstance(v, Digits):
        raise problem(422, _field((*path, key)) or field, f"a number of {int(v):,} digits; no field takes more than "
                                                          f"{INT_DIGITS:,}", "number", f"({int(v):,} digits)")
    elif isinstance(v, float):
        if not math.isfinite(v):
            raise problem(422, _field((*path, key)) or field, "must be a finite number (JSON has no NaN or Infinity)",
                          "finite_number", v)
    elif not (v is None or isinstance(v, (bool, int))):
        raise problem(422, _field((*path, key)) or field, f"must be a number, text, a list or a mapping, not "
                                                          f"YAML's {type(v).__name__}", "json_value", str(v))


def _finite_numbers(x: list) -> bool:
    """Whether every element is a finite float or an int of float range (a record of data):
    True lets the walk skip the list's elements; False sends it through them one by one,
    which names the first offending one."""
    if not set(map(type, x)) <= {float, int}:
        return False
    try:
        return bool(np.isfinite(np.asarray(x, dtype=float)).all())
    except OverflowError:  # an int past the float range
        return False


def check_input(raw: Any, max_values: int, field: str = "body") -> None:
    """One iterative walk over ``raw``: at most MAX_DEPTH levels and ``max_values`` values
    (413; a YAML alias counts each time it is used); every string Unicode text (a lone
    surrogate is valid JSON but no text), every number finite and of a convertible length,
    every key text, only JSON's kinds of values; and the names as :func:`check_names` says.
    422 naming the field."""
    stack: list[tuple[tuple, Any]] = [((), raw)]
    seen = 0
    while stack:
        path, x = stack.pop()
        if len(path) > MAX_DEPTH:  # named by its top-level field (the path itself is that long)
            raise problem(413, _field(path[:1]) or field, f"nests deeper than {MAX_DEPTH} levels", "too_deep")
        seen += len(x)
        if seen > max_values:
            raise problem(413, field, f"holds more than {max_values:,} values", "too_large")
        if isinstance(x, list) and len(x) > 64 and _finite_numbers(x):
            continue  # a record of numbers, checked at C speed
        items = x.items() if isinstance(x, dict) else enumerate(x)
        for k, v in items:
            if isinstance(x, dict) and not isinstance(k, str):  # YAML's 1: or null:
                raise problem(422, _field(path) or field, f"keys must be text, got {k!r}", "key", str(k))
            if isinstance(k, str):
                _scalar(k, path, k, field)  # a key may be what is wrong
            if isinstance(v, (list, dict)):
                stack.append(((*path, k), v))
            else:
                _scalar(v, path, k, field)
    if not isinstance(raw, dict):
        return
    names = [("name", raw.get("name"))]
    if isinstance(raw.get("models"), list):
        names += [(f"models[{i}].name", m.get("name")) for i, m in enumerate(raw["models"]) if isinstance(m, dict)]
    check_names([(where, name) for where, name in names if isinstance(name, str)])  # else the schema says


#: characters a name may not hold: control (Cc), format (Cf: bidi overrides, zero-width
#: spaces and joiners, the byte-order mark), line and paragraph separators, private-use and
#: unassigned code points: each is invisible or shown as something else, so one name could
#: look like another
HIDDEN = {"Cc": "control", "Cf": "invisible format", "Zl": "line separator", "Zp": "paragraph separator",
          "Co": "private-use", "Cn": "unassigned"}


def name_key(name: str) -> str:
    """What a name looks like: compatibility-normalised (NFKC: full-width letters, ligatures),
    case-folded, without surrounding space. Two names with one key are one name to a reader."""
    return unicodedata.normalize("NFKC", name).casefold().strip()


def check_names(names: list[tuple[str, str]]) -> None:
    """The job's and models' names (``(field, name)``): short, no hidden character
    (:data:`HIDDEN`), no surrounding space, and no two models' names that differ only by
    case or width (exact duplicates: ``abcns.run.check_models``). 422 naming the field."""
    seen: dict[str, tuple[str, str]] = {}
    for where, name in names:
        if len(name) > NAME_MAX_CHARS:
            raise problem(422, where, f"at most {NAME_MAX_CHARS} characters, got {len(name)}", "name", name)
        bad = next((c for c in name if unicodedata.category(c) in HIDDEN), None)
        if bad is not None:
            kind = HIDDEN[unicodedata.category(bad)]
            what = unicodedata.name(bad, "") or kind
            raise problem(422, where, f"must not hold {kind} characters (found U+{ord(bad):04X} {what}), which could "
                                      f"make one name look like another", "name", name)
        if name != name.strip():
            raise problem(422, where, "must not begin or end with a space", "name", name)
        if not where.startswith("models"):
            continue
        other = seen.setdefault(name_key(name), (where, name))
        if other[1] != name:
            raise problem(422, where, f"differs from {other[0]} ({other[1]!r}) only by case or width: give the models "
                                      "names that do not look alike", "name", name)


# ---------------------------------------------------------------------------- 4. the schema
def validate_spec(raw: Any, max_values: int, field: str = "body") -> JobSpec:
    if not isinstance(raw, dict):
        raise problem(422, field, "the job spec must be a JSON object (a mapping)", "json", raw)
    check_input(raw, max_values, field)
    try:
        return JobSpec.model_validate(raw)
    except ValidationError as err:
        raise Refused(422, validation_errors([{**e, "loc": ("body", *e["loc"])} for e in err.errors()])) from None


def spec_of(text: bytes, field: str, kind: str, max_values: int,
            upload: bool = False) -> tuple[JobSpec, dict[str, np.ndarray]]:
    """(the spec, its inline arrays) of a submitted body; ``kind``: "json", "yaml" or "any"
    (JSON when it parses as JSON, else YAML: an upload's spec part). Data come inline, or
    with ``upload`` as ``npz:KEY`` of the upload: never a file name (422 naming the field).
    Runs in the child."""
    if kind == "yaml" or (kind == "any" and not text.lstrip().startswith((b"{", b"["))):
        raw = parse_yaml(text, field)
    else:
        scan(text, field, max_values)
        raw = parse_json(text, field)
    return spec_and_arrays(raw, field, max_values, upload)


def study_of(text: bytes, max_values: int) -> tuple[JobSpec, dict[str, np.ndarray], dict]:
    """(the spec, its inline arrays, the study's other fields) of a POST /studies body: JSON
    whose ``spec`` is a job spec with its data inline (422 naming ``spec`` otherwise). Runs in
    the child, as :func:`spec_of`: a large body's parse never holds the service's event loop."""
    scan(text, "body", max_values)
    raw = parse_json(text, "body")
    if not isinstance(raw, dict) or not isinstance(raw.get("spec"), dict):
        raise problem(422, "spec", "missing: the job spec, an object with its data inline", "missing")
    spec, arrays = spec_and_arrays(raw.pop("spec"), "spec", max_values)
    return spec, arrays, raw


def spec_and_arrays(raw: Any, field: str, max_values: int,
                    upload: bool = False) -> tuple[JobSpec, dict[str, np.ndarray]]:
    """The spec validated, its inline records as arrays (their places in the spec renamed to
    the job's data file); files refused unless ``upload`` names its ``npz:KEY``."""
    spec = validate_spec(raw, max_values, field)
    arrays = {}
    for key in ("input", "observed", "voltage"):
        value = getattr(spec.data, key)
        if isinstance(value, list):
            arrays[key] = np.asarray(value, dtype=float)
        elif isinstance(value, str) and not (upload and value.startswith("npz:")):
            raise problem(422, f"data.{key}", "give the data inline" + (
                " or as npz:KEY of the upload" if upload else "; files are not allowed here (upload an .npz: "
                "POST /jobs/upload)"), "spec", value)
    if arrays:  # the lists stay here: the arrays travel back, and the job manager stores them
        spec = spec.model_copy(update={"data": spec.data.model_copy(update={k: f"{DATA_FILE}:{k}" for k in arrays})})
    return spec, arrays


PR_SET_PDEATHSIG = 1  # Linux prctl(2): a signal for this process when its parent dies


def _warm(parent: int | None = None) -> None:
    """The child's start: everything :func:`spec_of` imports is imported by now; on Linux it
    asks for SIGKILL when the service's process dies, however it dies (after a kill -9 it
    waited on its queue for ever, holding its ~150 MB, and the resource tracker with it)."""
    if parent is None or not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the service died before the request took hold
        os._exit(0)


# ---------------------------------------------------------------------------- the pool
class Intake:
    """Submissions handled at once (``slots``) and the child process that parses and
    validates them (one: its memory, with its imports, is paid once). ``async with
    intake.slot():`` around reading and handling a body; ``await intake.spec(...)`` in the
    child."""

    def __init__(self, slots: int, max_values: int):
        self.max_values = max_values
        self.processes = 1  # one child: a second submission's parse waits while the first one's job is built
        self._slots = asyncio.Semaphore(slots)
        self._uploads = asyncio.Semaphore(1)
        self._pool: ProcessPoolExecutor | None = None

    def pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.processes, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_warm, initargs=(os.getpid(),))
        return self._pool

    def start(self) -> None:
        """Start the children now (a spawned child imports the spec's modules: ~1-2 s), so the
        first submission does not wait for them."""
        pool = self.pool()
        for _ in range(self.processes):
            pool.submit(_warm)

    @asynccontextmanager
    async def slot(self):
        """A submission being read and handled (a bounded number at once)."""
        async with self._slots:
            yield

    @asynccontextmanager
    async def upload(self):
        """An upload's arrays being read and stored: one at a time (a record may hold
        ``max_array_samples`` samples, 8 bytes each, read once and again by the checks)."""
        async with self._uploads:
            yield

    async def spec(self, text: bytes, field: str, kind: str,
                   upload: bool = False) -> tuple[JobSpec, dict[str, np.ndarray]]:
        return await self._in_child(spec_of, text, field, kind, self.max_values, upload)

    async def study(self, text: bytes) -> tuple[JobSpec, dict[str, np.ndarray], dict]:
        """:func:`study_of` in the child."""
        return await self._in_child(study_of, text, self.max_values)

    async def _in_child(self, fn, *args):
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self.pool(), fn, *args)
        except BrokenExecutor:  # a child died (killed, out of memory): a new pool for the next one
            self._pool = None
            raise Refused(503, "the process that reads job specs stopped; try again", {"Retry-After": "5"}) from None
        except MemoryError:
            raise Refused(503, "no memory to read this job spec now; try again", {"Retry-After": "5"}) from None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
