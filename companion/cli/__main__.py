"""``python -m companion.cli``: the ``companion`` command line, as ``python -m companion``."""

from companion.cli import main

if __name__ == "__main__":
    main()
