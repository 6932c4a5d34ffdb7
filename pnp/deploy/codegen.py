"""Generates the protocol's Python code from ``proto/deploy.proto`` with grpcio-tools.

    python -m pnp.deploy.codegen           # rewrite pnp/deploy/proto/deploy_pb2*.py
    python -m pnp.deploy.codegen --check   # exit 1 if the committed files differ from a fresh generation

The generated files are committed (no build step at install); a test runs ``--check``.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

PROTO_DIR = Path(__file__).resolve().parent / "proto"
PROTO = PROTO_DIR / "deploy.proto"
GENERATED = ("deploy_pb2.py", "deploy_pb2_grpc.py")


def _fix_import(text: str) -> str:
    # grpcio-tools writes `import deploy_pb2` (a top-level module); ours lives in a package.
    return text.replace("import deploy_pb2 as deploy__pb2", "from pnp.deploy.proto import deploy_pb2 as deploy__pb2")


def generate(out_dir: Path) -> dict[str, str]:
    """The generated files' text, written to ``out_dir``."""
    from grpc_tools import protoc  # the [deploy] extra

    args = ["grpc_tools.protoc", f"-I{PROTO_DIR}", f"--python_out={out_dir}", f"--grpc_python_out={out_dir}", str(PROTO)]
    if protoc.main(args) != 0:
        raise RuntimeError(f"protoc failed on {PROTO}")
    texts = {name: _fix_import((out_dir / name).read_text()) for name in GENERATED}
    for name, text in texts.items():
        (out_dir / name).write_text(text)
    return texts


def stale() -> list[str]:
    """The committed generated files that differ from a fresh generation."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(Path(tmp))
    return [n for n, text in fresh.items() if not (PROTO_DIR / n).exists() or (PROTO_DIR / n).read_text() != text]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="compare instead of writing")
    args = parser.parse_args(argv)
    if args.check:
        bad = stale()
        print(f"stale: {bad} (run python -m pnp.deploy.codegen)" if bad else "generated code is current")
        return 1 if bad else 0
    generate(PROTO_DIR)
    print(f"wrote {', '.join(GENERATED)} in {PROTO_DIR}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
