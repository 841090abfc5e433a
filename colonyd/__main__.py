"""`python -m colonyd`: the same entry point as the `colonyd` console script."""

from colonyd.cli import launch

if __name__ == "__main__":
    launch()
