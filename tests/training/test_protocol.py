"""The evaluation protocol's seeds: roles and names."""
import pytest

from pnp.training.protocol import (
    DEVELOPMENT_SEED, REPORTING_SEED, SELECTION_SEEDS, TRAINING_SEEDS, resolve_seed, seed_role,
)


def test_roles_are_disjoint_and_named():
    assert REPORTING_SEED not in (*TRAINING_SEEDS, *SELECTION_SEEDS, DEVELOPMENT_SEED)
    assert seed_role(REPORTING_SEED) == "reporting" and seed_role(12345) == "development"
    assert [seed_role(s) for s in SELECTION_SEEDS] == ["selection"] * len(SELECTION_SEEDS)
    assert seed_role(5) == "other"


def test_seed_names_resolve_and_bad_names_are_refused():
    assert resolve_seed("reporting") == REPORTING_SEED and resolve_seed("development") == 12345
    assert resolve_seed(777) == 777 and resolve_seed("778") == 778
    with pytest.raises(ValueError, match="seed='final'"):
        resolve_seed("final")
