"""The committed generated code is what grpcio-tools makes of deploy.proto today."""
from __future__ import annotations

import pytest

pytest.importorskip("grpc_tools")


def test_generated_code_is_current():
    from pnp.deploy.codegen import stale

    assert stale() == [], "run: python -m pnp.deploy.codegen"
