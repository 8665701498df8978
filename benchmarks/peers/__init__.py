"""abcns and pyABC side by side on the paper's §3.1, §3.2 and §4.1 (issue G).

    python -m benchmarks.peers [--seeds 3] [--quick] [--out benchmarks/peers/RESULTS.md]

Needs the optional extra ``pip install -e '.[bench]'`` (pyABC). See :mod:`benchmarks.peers.__main__`.
"""
