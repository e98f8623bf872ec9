"""The structure search (`fitting.identify`, `piezojax fit --auto`): its candidates are valid CONFIGs, its split
and selection rule, and an end-to-end search on a plant written without piezojax code."""

import dataclasses
import itertools

import numpy as np
import pytest

import fitting
import piezojax as pj
from fitting._identify import structures as S
from fitting._identify.validation import Z, select, split

DT = 1e-3


def _records(n_records, n=1000):
    t = np.arange(n) * DT
    return fitting.Dataset([fitting.Experiment.from_arrays(t=t, v_in=np.sin(t * (i + 1)), displacement=np.cos(t),
                                                           name=f"r{i}") for i in range(n_records)])


def test_every_structure_the_search_writes_is_a_valid_config():
    """Each neighbour of each stage, from a few structures, parses; its tables are the structure's; a base CONFIG's
    tables are kept and not written twice."""
    seeds = [S.Structure(), dataclasses.replace(S.Structure(), creep="kelvin_voigt", creep_structure="series",
                                                dynamics=2), S.Structure("bouc_wen", creep="lag", prehistory=True)]
    moves = (S.creep_neighbours, S.dynamics_neighbours, S.hysteresis_neighbours, S.deeper_creep, S.extra_neighbours)
    seen = set()
    for seed, move in itertools.product(seeds, moves):
        for s in move(seed):
            if not s.valid() or s in seen:
                continue
            seen.add(s)
            cfg = fitting.parse_config(s.toml(), s.label())
            assert cfg.hysteresis == s.hysteresis and cfg.dynamics_order == s.dynamics
            assert cfg.creep == s.creep and (s.creep == "none" or cfg.creep_structure == s.creep_structure)
            assert ("delay.time" in cfg.default_free()) == s.delay
            assert ("prehistory" in cfg.default_free()) == s.prehistory
    assert {s.hysteresis for s in seen} == set(S.HYSTERESIS_KINDS) and len(seen) > 20
    base = '[creep]\nkind = "lag"\nlags = 2\nstructure = "series"\n[fit]\nmax_steps = 50\n'
    cfg = fitting.parse_config(S.Structure(creep="kelvin_voigt", dynamics=2).toml(base), "b")
    assert cfg.creep == "lag" and cfg.max_steps == 50 and cfg.dynamics_order == 2
    with pytest.raises(pj.PiezojaxValueError, match="observer"):
        S.fixed_tables('[observer]\nkind = "sensor_layer"\n')


def test_the_split_holds_out_the_end_of_every_record():
    parts = split(_records(2))
    assert [e.n for e in parts.training] == [700, 700]
    assert [(tail.n, history[0].n) for tail, history in parts.validation] == [(300, 700), (300, 700)]
    assert parts.validation[0][1][0].name == parts.training[0].name  # each end continues its own beginning
    short = fitting.Dataset([*_records(1), *(e.slice(None, 0.5, name="short") for e in _records(1))])
    parts = split(short)  # a record too short to leave a validation end is fitted whole
    assert [e.n for e in parts.training] == [700, 500] and len(parts.validation) == 1 and "short whole" in (
        parts.description)
    with pytest.raises(pj.PiezojaxValueError, match="too short"):
        split(_records(1, n=500))


def test_the_rule_keeps_the_simplest_within_the_uncertainty_of_the_best():
    rng = np.random.default_rng(0)
    noise = rng.standard_normal(4000)
    misfit = 0.3 * np.sin(np.arange(4000) / 50)  # a slow, correlated misfit
    best = noise  # at the noise
    close = noise + 0.01 * rng.standard_normal(4000)  # as good, within chance
    worse = noise + misfit  # clearly worse
    kept, within = select([close, best, worse], [5, 12, 3])
    assert kept == 0 and within == [True, True, False]
    kept, within = select([worse, best], [3, 12])  # the simpler one is clearly worse: the better one is kept
    assert kept == 1 and within == [False, True]
    kept, _ = select([np.full(10, np.nan), best[:10]], [1, 5])  # a candidate that failed is never kept
    assert kept == 1
    assert Z == 2.0
    # a misfit that varies over time is not chance: 6x the noise is never within the uncertainty of 1.1x
    ringing = noise + 6 * np.sin(np.arange(4000) / 7) * (np.arange(4000) % 1000 < 200)
    kept, within = select([ringing, noise + 0.4 * np.sin(np.arange(4000) / 30)], [5, 12])
    assert kept == 1 and within == [False, True]


def test_fit_auto_arguments_are_checked(tmp_path, capsys):
    from fitting.cli import main

    config = tmp_path / "c.toml"
    config.write_text('[hysteresis]\nkind = "prandtl_ishlinskii"\n')
    assert main(["fit", str(config), "--out", str(tmp_path / "o")]) == 2
    assert "required: DATA" in capsys.readouterr().err
    assert main(["fit", str(config), "a.csv", "--config", str(config), "--out", str(tmp_path / "o")]) == 2
    assert "use it with --auto" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
