"""``python -m ablations.sweep``: the ``ablate-sweep`` command."""

from ablations.sweep.driver import main

if __name__ == "__main__":
    main()
