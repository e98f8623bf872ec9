"""The structure search (`fitting.identify`, `piezojax fit --auto`): its candidates are valid CONFIGs, its split
and selection rule, the warm start of a candidate from its parent, and the command's arguments."""

import dataclasses
import itertools

import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
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
                                                dynamics=2), S.Structure("bouc_wen", creep="lag", prehistory=True),
             S.Structure("play", dynamics=1)]
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
            if s.dynamics:
                o = cfg.dynamics_options
                assert 2 * o.zero_pairs + o.real_zeros == s.zeros
    assert {s.hysteresis for s in seen} == set(S.HYSTERESIS_KINDS) and len(seen) > 20
    assert {s.zeros for s in seen} == {0, 1, 2}  # a real zero after one pole, an antiresonance after a pair
    # one CONFIG, one structure: what the CONFIG does not write does not make another candidate
    texts = {}
    for s in seen:
        texts.setdefault(s.toml(), set()).add(s.normal())
    assert all(len(v) == 1 for v in texts.values()) and len(texts) < len(seen)
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
    # a base may give only how the records are read; a bad one is named
    base = fitting._identify.parse_base('[data]\nunits = {displacement = "um"}\n', "data.toml")
    assert base.data["units"] == {"displacement": "um"} and base.hysteresis == S.Structure().hysteresis
    bad = tmp_path / "bad.toml"
    bad.write_text('[data]\nunits = {displacement = "furlong"}\n')
    assert main(["fit", "--auto", "a.csv", "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "furlong" in err and not (tmp_path / "o").exists()


def test_a_candidate_starts_from_its_parents_fitted_blocks():
    """`warm_start`: the blocks a candidate shares with its parent (same type, shapes and creep structure) start
    at the parent's fitted values, through the CONFIG's reparametrisation; the others keep their own start."""
    from fitting._identify.search import shared_blocks, warm_start

    t = np.arange(3000) * DT
    v = 50 * np.sin(2 * np.pi * 2 * t) * np.minimum(1, t / 0.3)
    rec = fitting.Experiment.from_arrays(t=t, v_in=v, displacement=1e-8 * v + 1e-9 * np.sin(9 * t), name="r")
    parent = S.Structure("prandtl_ishlinskii", 4, creep="kelvin_voigt", creep_structure="series", dynamics=2)
    pcfg = fitting.parse_config(parent.toml(), "parent")
    fitted = pj.unwrap(pcfg.starts(fitting.Dataset([rec]))[0])
    fitted = eqx.tree_at(lambda m: (m.hysteresis.weights, m.creep.time_constants, m.offset), fitted,
                         (fitted.hysteresis.weights * 1.7, fitted.creep.time_constants * 3.0, jnp.asarray(2e-7)))
    for child, shared, own in [
        (dataclasses.replace(parent, dynamics=4), ("hysteresis", "creep", "offset"), ("dynamics",)),
        (dataclasses.replace(parent, creep_structure="parallel"), ("hysteresis", "dynamics", "offset"), ("creep",)),
        (dataclasses.replace(parent, hysteresis="play"), ("creep", "dynamics", "offset"), ("hysteresis",)),
        (dataclasses.replace(parent, polynomial=2), ("creep", "dynamics", "offset"), ()),
    ]:
        cfg = fitting.parse_config(child.toml(), child.label())
        start = cfg.starts(fitting.Dataset([rec]))[0]
        warm = warm_start(cfg, start, fitted, shared_blocks(child, parent))
        assert jtu.tree_structure(warm) == jtu.tree_structure(start)  # fitted together with the data-driven start
        got, own_start = pj.unwrap(warm), pj.unwrap(start)
        for name in shared:
            for a, b in zip(jtu.tree_leaves(getattr(got, name)), jtu.tree_leaves(getattr(fitted, name))):
                np.testing.assert_allclose(a, b, rtol=1e-12)
        for name in own:
            for a, b in zip(jtu.tree_leaves(getattr(got, name)), jtu.tree_leaves(getattr(own_start, name))):
                np.testing.assert_allclose(a, b, rtol=1e-12)  # (through the reparametrisation and back)
        if child.polynomial:  # the parent's operator inside the added output polynomial
            np.testing.assert_allclose(got.hysteresis.hysteresis.weights, fitted.hysteresis.weights, rtol=1e-12)


def test_calibrate_fits_the_starts_a_caller_makes():
    """`calibrate(..., starts=fn)`: `fn(config, dataset)` makes the starts fitted together (here the rule-based
    start alone, without the joint cold start); none is refused with one line."""
    t = np.arange(1500) * DT
    v = 40 * np.sin(2 * np.pi * 3 * t) * np.minimum(1, t / 0.2)
    truth = pj.Actuator(pj.PrandtlIshlinskii(jnp.asarray([2e-8, 1e-8]), jnp.asarray([0.0, 15.0])))
    y = np.asarray(truth.simulate(jnp.asarray(v), DT).displacement)
    rec = fitting.Experiment.from_arrays(t=t, v_in=v, displacement=y + 1e-10 * np.sin(50 * t), name="r")
    cfg = fitting.parse_config('[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 2\n[fit]\nmax_steps = 60\n', "c")
    made = []

    def own(config, dataset):
        made.append((config, dataset))
        return config.starts(dataset, cold_start=False)

    cal = fitting.calibrate(cfg, rec, starts=own, progress=False, refine_rounds=False)
    assert made[0][0] is cfg and [e.name for e in made[0][1]] == ["r"]
    assert cal.result.starts is None and cal.result.cost < cal.result.initial_cost  # one start: no multi-start table
    with pytest.raises(pj.PiezojaxValueError, match="returned no start"):
        fitting.calibrate(cfg, rec, starts=lambda c, d: [], progress=False)


def test_added_zeros_start_around_the_parents_fitted_poles():
    """A candidate that adds zeros to its parent's dynamics starts from the parent's fitted poles and gain, each
    zero pair at 1.25 times its pole pair's frequency with its damping (the CONFIG's rule around the fitted poles);
    the extra stages add one part at a time to the structure kept so far."""
    from fitting._identify.search import shared_blocks, warm_start

    t = np.arange(3000) * DT
    v = 50 * np.sin(2 * np.pi * 2 * t) * np.minimum(1, t / 0.3)
    rec = fitting.Dataset([fitting.Experiment.from_arrays(t=t, v_in=v, displacement=1e-8 * v, name="r")])
    parent = S.Structure("prandtl_ishlinskii", 4, dynamics=2)
    fitted = pj.unwrap(fitting.parse_config(parent.toml(), "p").starts(rec)[0])
    fitted = eqx.tree_at(lambda m: (m.dynamics.omega, m.dynamics.zeta), fitted,
                         (jnp.asarray([2 * np.pi * 321.0]), jnp.asarray([0.07])))
    child = dataclasses.replace(parent, zeros=2)
    cfg = fitting.parse_config(child.toml(), "c")
    assert shared_blocks(child, parent) == {"hysteresis", "creep", "offset", "prehistory", "delay", "dynamics poles"}
    got = pj.unwrap(warm_start(cfg, cfg.starts(rec)[0], fitted, shared_blocks(child, parent))).dynamics
    np.testing.assert_allclose(got.omega, [2 * np.pi * 321.0], rtol=1e-12)
    np.testing.assert_allclose(got.zero_omega, [1.25 * 2 * np.pi * 321.0], rtol=1e-12)
    np.testing.assert_allclose(got.zero_zeta, [0.07], rtol=1e-12)
    kept = dataclasses.replace(parent, zeros=2, polynomial=2)
    assert S.extra_neighbours(kept, "prehistory") == [dataclasses.replace(kept, prehistory=True)]
    assert S.extra_neighbours(kept, "zeros") == [] and len(S.extra_neighbours(parent)) == 5
    assert S.extra_neighbours(parent, "elements") == [dataclasses.replace(parent, elements=8)]
    assert S.extra_neighbours(dataclasses.replace(parent, elements=16), "elements") == []
    # twice the plays: the child starts where its parent ended (its plays kept, new ones between them, nearly dead)
    more = dataclasses.replace(parent, elements=8, polynomial=2)
    poly_parent = dataclasses.replace(parent, polynomial=2)
    assert "hysteresis plays" in shared_blocks(more, poly_parent)
    fitted = pj.unwrap(fitting.parse_config(poly_parent.toml(), "p").starts(rec)[0])
    cfg = fitting.parse_config(more.toml(), "c")
    child = pj.unwrap(warm_start(cfg, cfg.starts(rec)[0], fitted, shared_blocks(more, poly_parent)))
    r = np.asarray(fitted.hysteresis.hysteresis.thresholds)
    got = child.hysteresis.hysteresis
    np.testing.assert_allclose(got.thresholds, np.sort(np.r_[r, 0.5 * (r[1:] + r[:-1]), 1.5 * r[-1] - 0.5 * r[-2]]),
                               rtol=1e-12)
    np.testing.assert_allclose(child.hysteresis.coefficients, fitted.hysteresis.coefficients, rtol=1e-12)
    x = jnp.asarray(v)
    y_parent, y_child = np.asarray(fitted.hysteresis(x)), np.asarray(child.hysteresis(x))
    assert np.max(np.abs(y_child - y_parent)) < 5e-3 * np.ptp(y_parent)


def test_a_preisach_candidates_grid_covers_the_records_span_and_one_row_below():
    """The search lays a Preisach candidate's grid on the records' voltages: every level switches within them
    except the lowest row, whose relays never switch off once on (the kind's default grid, symmetric about 0,
    would leave half its levels unused on unipolar drives)."""
    lo, hi = S.preisach_range(0.0, 100.0, 8)
    grid = pj.Preisach.uniform(lo, hi, 8)
    alpha, beta = np.unique(np.asarray(grid.alpha)), np.unique(np.asarray(grid.beta))
    assert alpha.size == beta.size == 8
    assert beta[0] < 0.0 < beta[1] and alpha[-1] < 100.0 and np.all(alpha[1:] > 0.0)
    cfg = fitting.parse_config(S.Structure("preisach", 8).toml("", inputs=(0.0, 100.0)), "c")
    assert cfg.hysteresis_options.range == (lo, hi)


def test_the_table_says_when_no_structure_reached_the_noise():
    """A search whose best candidate predicts the validation samples at 1.2 times the noise or more says that no
    structure reached it (a plant outside the searched classes); one at about 1 does not."""
    from fitting._identify.search import Candidate, Identification

    def table(scores):
        cands = [Candidate(S.Structure("prandtl_ishlinskii", 8, dynamics=d), None, 20 + d, v, v, "successful", 1.0,
                           np.zeros(3)) for d, v in enumerate(scores)]
        ident = Identification(None, cands, 0, [True] + [False] * (len(cands) - 1), "split", 10.0, 2.0)
        return ident.table(), ident.reached_noise

    text, reached = table([4.97, 6.1])
    assert not reached
    assert ("no structure reached the noise in validation: the best, PI(8), predicts the validation samples at "
            "4.97x") in text
    text, reached = table([1.03, 6.1])
    assert reached and "no structure reached the noise" not in text
