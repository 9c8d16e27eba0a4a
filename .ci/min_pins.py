"""Print `name==version` pins for the lower bounds declared in pyproject.toml.

Used by `make test-min`: the runtime dependencies (and the `plot` extra) are
installed at exactly the oldest versions jaxnh declares, so a bound that is
not true fails there. Every runtime dependency must carry a `>=` bound.
"""

import re
import sys
import tomllib
from pathlib import Path


def main() -> int:
    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
    specs = list(project["dependencies"]) + list(project["optional-dependencies"]["plot"])
    for spec in specs:
        m = re.fullmatch(r"\s*([A-Za-z0-9_.\-]+)(\[[^\]]*\])?\s*>=\s*([0-9][^,;\s]*)\s*(,.*)?", spec)
        if m is None:
            print(f"min_pins: dependency {spec!r} has no '>=' lower bound", file=sys.stderr)
            return 1
        print(f"{m.group(1)}{m.group(2) or ''}=={m.group(3)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
