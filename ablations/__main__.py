"""``python -m ablations {ablate,memory,plot,report} ...``: the console scripts without installing them."""

from __future__ import annotations

import sys

from ablations.cli import ablate_main, memory_main, plot_main, report_main

COMMANDS = {"ablate": ablate_main, "memory": memory_main, "plot": plot_main, "report": report_main}


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in COMMANDS:
        print(f"usage: python -m ablations {{{','.join(COMMANDS)}}} [--help | args...]", file=sys.stderr)
        raise SystemExit(2)
    COMMANDS[sys.argv[1]](sys.argv[2:])


if __name__ == "__main__":
    main()
