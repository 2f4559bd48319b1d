"""Phenotypes by name, values or seed, and the scenario settings that choose the body."""

from __future__ import annotations

import pytest

from torchmocap.body import PHENOTYPE_NAMES, PhenotypeError
from torchmocap.body.phenotypes import (
    RANDOM_RANGES,
    named_phenotypes,
    random_phenotype,
    resolve_phenotype,
)
from torchmocap.data.synthetic.scenario import ScenarioError, load_scenario


def test_named_and_mapping_fill_the_rest_with_the_default():
    child = resolve_phenotype("child")
    assert child["age"] == named_phenotypes()["child"]["age"] < 0.5
    assert set(child) == set(PHENOTYPE_NAMES)
    assert resolve_phenotype({"weight": 0.9}) == {**dict.fromkeys(PHENOTYPE_NAMES, 0.5),
                                                  "weight": 0.9}
    assert resolve_phenotype(None) == resolve_phenotype("default")
    # the named bodies the experiments use differ from the default and from each other
    named = [tuple(resolve_phenotype(n).values()) for n in ("child", "heavy", "slim", "tall",
                                                           "female", "male")]
    assert len(set(named)) == len(named)


def test_random_is_reproducible_and_spans_its_ranges():
    assert random_phenotype(3) == random_phenotype(3) == resolve_phenotype("random", seed=3)
    draws = [random_phenotype(s) for s in range(40)]
    assert len({tuple(d.values()) for d in draws}) == 40
    for name in PHENOTYPE_NAMES:
        vals = [d[name] for d in draws]
        lo, hi = RANDOM_RANGES[name]
        if name == "gender":  # both sexes
            assert min(vals) <= 0.2 and max(vals) >= 0.8
        else:
            assert lo <= min(vals) and max(vals) <= hi
            assert max(vals) - min(vals) > 0.5 * (hi - lo)


@pytest.mark.parametrize("spec, words", [
    ("giant", ["phenotype", "giant", "child"]),
    ({"wieght": 0.3}, ["unknown parameter", "wieght"]),
    ({"weight": 1.5}, ["phenotype.weight", "[0, 1]", "1.5"]),
    ({"age": -0.1}, ["phenotype.age"]),
    ({"age": "old"}, ["phenotype.age"]),
    (3, ["phenotype", "int"]),
])
def test_bad_phenotypes_are_named(spec, words):
    with pytest.raises(PhenotypeError) as e:
        resolve_phenotype(spec)
    for w in words:
        assert w in str(e.value)
    assert isinstance(e.value, ValueError)


def test_scenario_settings_are_validated():
    sc = load_scenario("clean", body="anny", phenotype={"weight": 0.8})
    assert sc.phenotype == {"weight": 0.8}
    assert load_scenario("clean").body == "skinned" and load_scenario("clean").phenotype is None
    with pytest.raises(ScenarioError, match=r"scenario\.phenotype.*giant"):
        load_scenario("clean", body="anny", phenotype="giant")
    with pytest.raises(ScenarioError, match=r"scenario\.phenotype\.height.*\[0, 1\]"):
        load_scenario("clean", body="anny", phenotype={"height": 2})
    with pytest.raises(ScenarioError, match=r"scenario\.phenotype.*unless body is 'anny'"):
        load_scenario("clean", phenotype="child")
    with pytest.raises(ScenarioError, match=r"scenario\.body.*'anny'"):
        load_scenario("clean", body="smpl")
