#!/usr/bin/env bash
# Issue U's 16-core targets, prepared for a session that is lent the device machine (16 cores,
# Python 3.12 with numpy, scipy, numba, pandas, xarray; no network there).
#
# Here, once (any machine with pip and the network; fills the ignored folder .whl/, ~16 MiB):
#     benchmarks/device_u.sh download
# Then one call of the device tool, carrying .whl (about 5-7 minutes; under 9):
#     run(command="bash benchmarks/device_u.sh", carry=[".whl"], timeout_s=600)
# Its figures come back under $OUT (u-*.txt), each beginning with the command that made it:
#   u-jobs.txt     32 §4.1 jobs on 14 workers: one after another in one process, run_jobs,
#                  `abcns serve`, 14 plain processes (targets: >= 10x one process); CPU per
#                  job and the workers' idle time between jobs, for run_jobs and the service
#   u-sleepy.txt   8 (then 16) sleepy 2 ms jobs on 14 workers together: the utilization
#   u-model.txt    the cluster model's queue mode for the sleepy rows (predicted before measured)
#   u-env.txt      the machine: cores, load, Python and package versions, the simulator's speed
set -uo pipefail
cd "$(dirname "$0")/.."
REPO=$PWD
WHEELS=(dask==2026.8.0 distributed==2026.8.0 zarr==3.1.6 numcodecs==0.16.6 donfig==0.8.1.post1
        google-crc32c==1.9.0 pydantic==2.14.4 pydantic-core==2.50.5 pydantic-settings==2.16.3
        python-dotenv==1.2.4 typing-inspection==0.4.5 annotated-types==0.8.0 typer==0.29.2
        tornado==6.6.1 tblib==3.2.2 zict==3.0.0 locket==1.0.0 partd==1.4.2 fastapi==0.165.0
        starlette==1.10.0 uvicorn==0.54.0 python-multipart==0.0.34 opentelemetry-api==1.45.2
        simpy==4.1.2)

if [[ "${1:-}" == "download" ]]; then
    # every other need of these (numpy, click, cloudpickle, msgpack, psutil, toolz, pyyaml,
    # fsspec, packaging, jinja2, anyio, h11, httpx, rich, shellingham, sortedcontainers,
    # typing-extensions, annotated-doc, ...) is in the device's image (KINDS.md)
    grep -qx '/.whl/' .gitignore || echo '/.whl/' >> .gitignore
    python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64 --platform any -d .whl "${WHEELS[@]}"
    du -sh .whl
    exit
fi

OUT=${OUT:-$REPO/benchmarks/out/device-u}
mkdir -p "$OUT"
START=$SECONDS
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$REPO PYTHONUNBUFFERED=1
PY=$(python3 -c 'import sys; print(sys.executable)')
BIN=$(dirname "$PY")
# benchmarks.harness starts `dask` and `abcns` beside sys.executable, with PYTHONPATH set to the
# repository alone: two small launchers there that find the carried packages themselves
for cmd in "dask:dask.__main__" "abcns:service.cli"; do
    name=${cmd%%:*}
    [[ -e "$BIN/$name" ]] && continue
    printf '#!%s\nimport sys\nsys.path[:0] = ["/tmp/site", "%s"]\nfrom %s import main\nsys.exit(main())\n' \
        "$PY" "$REPO" "${cmd#*:}" > "$BIN/$name"
    chmod +x "$BIN/$name"
done

run() {  # run FILE LIMIT_S COMMAND...: the command and its output into $OUT/FILE, stopped after LIMIT_S
    local file=$1 limit=$2
    shift 2
    echo "== $* ($(date -u +%H:%M:%S), load $(cut -d' ' -f1-3 /proc/loadavg), $((SECONDS - START)) s in)" | tee -a "$OUT/$file"
    timeout "$limit" "$@" 2>&1 | tee -a "$OUT/$file"
}

{
    nproc; cat /proc/loadavg; "$PY" -V
    "$PY" -c 'import numpy, scipy, numba, dask, distributed, zarr, pydantic, fastapi; print(numpy.__version__, scipy.__version__, numba.__version__, dask.__version__, zarr.__version__, pydantic.__version__, fastapi.__version__)'
} > "$OUT/u-env.txt" 2>&1
# the model first: its queue rows for what is measured below, predicted before it is (CPU only,
# seconds; its 64- and 256-worker rows take minutes and need no device: docs/benchmarks.md)
run u-model.txt 60 "$PY" -m benchmarks.cluster_model queue --workers 14,14 --jobs 8,16 --trace evidence-1000-warm --sleep-ms 2
# the simulator's speed here (the model's costs are carried from the earlier 16-core sessions)
run u-env.txt 60 "$PY" -m benchmarks.runner --populations 10 --repeats 1 --workers 1
run u-jobs.txt 270 "$PY" -m benchmarks.jobs --jobs 32 --workers 14 --ceiling --service
run u-sleepy.txt 75 "$PY" -m benchmarks.jobs --sleepy 2 --jobs 8 --workers 14
run u-sleepy.txt 75 "$PY" -m benchmarks.jobs --sleepy 2 --jobs 16 --workers 14
echo "done in $((SECONDS - START)) s" | tee -a "$OUT/u-env.txt"
