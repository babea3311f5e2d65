"""``python -m sitl``: the same as the ``sitl`` console script."""

from sitl.cli import main

if __name__ == "__main__":
    main()
