"""Regenerate sparkplug_b_pb2.py from sparkplug_b.proto (needs grpcio-tools; run once, commit).

    python -m gateway.outputs.sparkplug.gen

The runtime needs only ``protobuf`` (pinned in pyproject.toml to the generated code's major
version and at least its minor version, which the generated code checks when it is imported).
"""
from __future__ import annotations

import os
import sys


def main() -> int:
    from grpc_tools import protoc  # noqa: PLC0415 - a tool dependency, not a runtime one

    here = os.path.dirname(os.path.abspath(__file__))
    return protoc.main(["protoc", f"-I{here}", f"--python_out={here}", os.path.join(here, "sparkplug_b.proto")])


if __name__ == "__main__":
    sys.exit(main())
