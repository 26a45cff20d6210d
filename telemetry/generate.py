"""Generate the Python MAVLink module of the ngnav dialect with pymavlink's mavgen.

The dialect (``telemetry/dialects/ngnav.xml``) includes ``common.xml``; mavgen
is given the copy of ``common.xml`` (and its includes) that ships with the
installed pymavlink, so the generated module matches the pinned pymavlink.
Wire protocol 2.0: mavgen's default is 1.0, which cannot carry ids above 255
and would silently drop the dialect's messages (54000-54004).

The generated module is committed as ``telemetry/ngnav_mavlink.py``; the test
suite regenerates it into a temporary directory and compares byte for byte.
Regenerate after editing the XML or changing pymavlink::

    python -m telemetry.generate
"""

from __future__ import annotations

import contextlib
import io
import shutil
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: The dialect definition.
DIALECT_XML = HERE / "dialects" / "ngnav.xml"
#: The committed generated module.
GENERATED = HERE / "ngnav_mavlink.py"
#: The files common.xml includes, taken from the installed pymavlink.
_INCLUDES = ("common.xml", "standard.xml", "minimal.xml")


def generate(output: Path) -> Path:
    """Run mavgen (Python 3, MAVLink 2, validated) on the dialect; returns the .py path.

    Parameters
    ----------
    output : Path
        Where to write the module (a ``.py`` file path).
    """
    import pymavlink
    from pymavlink.generator import mavgen
    from pymavlink.generator.mavparse import PROTOCOL_2_0

    defs = Path(pymavlink.__file__).resolve().parent / "dialects" / "v20"
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for name in _INCLUDES:
            shutil.copyfile(defs / name, work / name)
        xml = work / DIALECT_XML.name
        shutil.copyfile(DIALECT_XML, xml)
        opts = mavgen.Opts(
            str(work / "ngnav_mavlink"),
            wire_protocol=PROTOCOL_2_0,
            language="Python3",
            validate=True,
        )
        log = io.StringIO()
        with contextlib.redirect_stdout(log):
            ok = mavgen.mavgen(opts, [str(xml)])
        if not ok:
            raise RuntimeError(f"mavgen failed on {DIALECT_XML}:\n{log.getvalue()}")
        out = Path(output)
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(work / "ngnav_mavlink.py", out)
    return Path(output)


def main(argv: list[str] | None = None) -> int:
    """``python -m telemetry.generate [OUT]``: regenerate the committed module."""
    args = sys.argv[1:] if argv is None else argv
    out = Path(args[0]) if args else GENERATED
    generate(out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
