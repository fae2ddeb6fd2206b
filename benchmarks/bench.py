"""Benchmark every backend mode on this machine; the same as `gcdtrav bench`.

python benchmarks/bench.py [--runs 7] [--zenoh-frames 100] [--out benchmarks/results/bench.json]
"""

import sys

from gcdtrav.service.bench import main

if __name__ == "__main__":
    sys.exit(main())
