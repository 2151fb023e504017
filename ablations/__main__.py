"""``python -m ablations {ablate,memory,plot,report,sweep,paper} ...``: the console scripts without installing them.

Each command's module is imported when it is called: ``ablate`` must start before torch is imported
(``ablations.startup``).
"""

from __future__ import annotations

import importlib
import sys

#: command -> "module:function", as pyproject.toml's [project.scripts] names them (ablate-<command>).
COMMANDS = {"ablate": "ablations.cli:ablate_main", "memory": "ablations.cli:memory_main",
            "plot": "ablations.cli:plot_main", "report": "ablations.cli:report_main",
            "sweep": "ablations.sweep:main", "paper": "ablations.paper:main", "plan": "ablations.cli:plan_main"}


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in COMMANDS:
        print(f"usage: python -m ablations {{{','.join(COMMANDS)}}} [--help | args...]", file=sys.stderr)
        raise SystemExit(2)
    module, function = COMMANDS[sys.argv[1]].split(":")
    try:
        entry = getattr(importlib.import_module(module), function)
    except KeyboardInterrupt:  # Ctrl-C while the command's module is imported: nothing has started
        print(f"interrupted while starting {sys.argv[1]}; nothing was written", file=sys.stderr)
        raise SystemExit(130) from None
    entry(sys.argv[2:])


if __name__ == "__main__":
    main()
