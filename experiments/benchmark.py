"""``python -m experiments.benchmark``: speed against peers measured in the same run (``benchmarks.benchmark``)."""

from benchmarks.benchmark import main

if __name__ == "__main__":
    main()
