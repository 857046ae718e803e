"""Regenerate protos/*_pb2.py, *_pb2_grpc.py and .pyi stubs from the .proto files.

Run `python protos/generate.py` after editing a .proto; commit the output.
"""

from __future__ import annotations

import logging
import re
import sys
from pathlib import Path

from grpc_tools import protoc

HERE = Path(__file__).resolve().parent
log = logging.getLogger(__name__)


def _proto_include() -> str:
    """grpc_tools ships the well-known types (struct.proto, ...)."""
    import grpc_tools

    return str(Path(grpc_tools.__file__).parent / "_proto")


def generate() -> list[Path]:
    protos = sorted(HERE.glob("*.proto"))
    args = ["grpc_tools.protoc", f"-I{HERE}", f"-I{_proto_include()}",
            f"--python_out={HERE}", f"--pyi_out={HERE}", f"--grpc_python_out={HERE}",
            *map(str, protos)]
    rc = protoc.main(args)
    if rc != 0:
        raise SystemExit(f"protoc failed with exit code {rc} for {[p.name for p in protos]}")
    stems = [p.stem for p in protos]
    out = []
    for path in sorted(HERE.glob("*_pb2*.py")) + sorted(HERE.glob("*_pb2.pyi")):
        text = path.read_text()
        # protoc emits `import nprt_pb2 as ...`, which only works with protos/ on sys.path.
        for stem in stems:
            text = re.sub(rf"^import {stem}_pb2 as ", f"from . import {stem}_pb2 as ",
                          text, flags=re.M)
        path.write_text(text)
        out.append(path)
    return out


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for p in generate():
        log.info("wrote %s", p.relative_to(HERE.parent))
    sys.exit(0)
