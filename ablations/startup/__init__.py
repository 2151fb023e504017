"""The start-up wing: everything an ``ablate`` process does so that its first iterations come soon.

Python's bytecode kept where the install keeps none (``bytecode``), the compile cache (``cache``), compile helper
processes for a cold GPU start (``helpers``), compiling the physics ahead (``ahead``), and the compile statistics
read from torch's own records with the progress display's texts (``stats``), behind one object, :class:`Startup`,
that ``ablate`` and ``ablations.runs`` call at a few named points (docs/design.md, "Start-up"). Importing this
package imports nothing heavy: its first point runs before torch is imported.
"""

from ablations.startup.bytecode import resolve_bytecode_folder
from ablations.startup.stats import compiled_graphs
from ablations.startup.wing import Startup

__all__ = ["Startup", "compiled_graphs", "resolve_bytecode_folder"]
