"""A model variant is plain data: a TOML file and its Python twin are the same model, a bad key
is named in the error, and a user's registered emission fits through the config by name."""

import dataclasses

import numpy as np
import pytest

from npbrs.domains.demos import Demonstrations
from npbrs.domains.mdp import TabularMDP
from npbrs.inference import EmissionConfig, Hyperparameter, ModelConfig, PriorConfig, SamplerConfig, fit, load
from npbrs.inference import hungarian_accuracy
from npbrs.models.emissions import EMISSIONS, PolicyEmission, register_emission

from npbrs.inference.driver import compiled as compiled_module
from npbrs.inference.driver.fit import OPTIONS, resolve_config

VARIANT = """
max_skills = 5

[emission]
name = "policy"

[emission.options]
concentration = 0.25

[prior]
alpha = 2.0
gamma = 0.5

[prior.kappa]
value = 8.0
shape = 2.0
rate = 0.25

[sampler]
chains = 3
samples = 50
warmup = 10
seed = 7
chain_method = "sequential"
init_skills = 2
init_window = 12

[sampler.moves]
birth_death = 1
"""

TWIN = ModelConfig(
    emission=EmissionConfig("policy", {"concentration": 0.25}),
    prior=PriorConfig(alpha=2.0, kappa=Hyperparameter(8.0, shape=2.0, rate=0.25), gamma=0.5),
    max_skills=5,
    sampler=SamplerConfig(chains=3, samples=50, warmup=10, seed=7, chain_method="sequential", init_skills=2,
                          init_window=12, moves={"birth_death": 1}))


def test_a_toml_variant_equals_its_python_twin(tmp_path):
    path = tmp_path / "variant.toml"
    path.write_text(VARIANT)
    cfg = ModelConfig.from_toml(path)
    assert cfg == TWIN
    assert cfg.prior.hyperpriors == {"kappa": (2.0, 0.25)}
    # and back: to_toml, to_dict and from_dict lose nothing
    assert ModelConfig.from_toml_string(TWIN.to_toml()) == TWIN
    assert ModelConfig.from_dict(TWIN.to_dict()) == TWIN
    TWIN.to_toml(tmp_path / "written.toml")
    assert ModelConfig.from_toml(tmp_path / "written.toml") == TWIN


def test_defaults_fill_missing_keys_and_nested_options_survive_toml():
    cfg = ModelConfig.from_toml_string('[emission]\nname = "policy"\n')
    assert cfg == ModelConfig(emission="policy")
    options = {"weights": [1.5, -2.0], "solver": {"tol": 1e-8, "name": 'a"b'}, "flag": True, "big": float("inf")}
    odd = ModelConfig(emission=EmissionConfig("policy", options))
    assert ModelConfig.from_toml_string(odd.to_toml()) == odd


def test_the_initial_windows_are_the_emissions_unless_the_configuration_sets_them():
    """``init_window`` left open: ``fit`` takes the emission's (5 steps for rewards of one weight
    per state, whose windows are each fitted at the start), else the kernel's 25, and records
    it; a value the configuration gives wins, and bad ones are refused by name."""
    from gridworld import gridworld

    from npbrs.inference import make_emission
    from npbrs.inference.driver.compiled import default_moves
    from npbrs.inference.sampler.kernel import initial_window

    dom = gridworld(size=5)  # 25 states
    onehot = TabularMDP.from_dense(dom.mdp.dense_transitions(), features=np.eye(25))
    assert SamplerConfig().init_window is None and "init_window" not in ModelConfig().to_toml()
    for mdp, emission, window in ((onehot, "reward", 5), (dom.mdp, "reward", 25), (onehot, "policy", 25)):
        em = make_emission(emission, mdp)
        cfg = default_moves(ModelConfig(emission=emission), em)
        assert cfg.sampler.init_window == window, (emission, mdp.num_features)
        assert initial_window(em) == window and initial_window(em, 12) == 12  # the kernel's, used directly
        given = ModelConfig(emission=emission, sampler=SamplerConfig(init_window=12))
        assert default_moves(given, em).sampler.init_window == 12
        assert ModelConfig.from_toml_string(cfg.to_toml()) == cfg  # the resolved value round-trips
    with pytest.raises(ValueError, match="sampler.init_window: expected an integer >= 1"):
        SamplerConfig(init_window=0)


def test_the_initial_skills_are_every_slot_for_one_weight_per_state_unless_the_configuration_sets_them():
    """``init_skills`` left open: every slot for rewards of more than 16 weights (a start with
    fewer skills than the data lumps goals into one, as on the rooms world), else
    half of them, as the kernel takes it too; ``fit`` records it; a given value wins, and one
    above ``max_skills`` is refused by name."""
    from gridworld import gridworld

    from npbrs.inference import make_emission
    from npbrs.inference.driver.compiled import default_moves
    from npbrs.inference.sampler.kernel import BPHMMKernel, initial_skills
    from npbrs.models.emissions import HMMData

    dom = gridworld(size=5)  # 25 states
    onehot = TabularMDP.from_dense(dom.mdp.dense_transitions(), features=np.eye(25))
    assert SamplerConfig().init_skills is None and "init_skills" not in ModelConfig().to_toml()
    for mdp, emission, K, skills in ((onehot, "reward", 6, 6), (onehot, "reward", 5, 5), (dom.mdp, "reward", 6, 3),
                                     (dom.mdp, "reward", 5, 3), (onehot, "policy", 6, 3)):
        em = make_emission(emission, mdp)
        cfg = default_moves(ModelConfig(emission=emission, max_skills=K), em)
        assert cfg.sampler.init_skills == skills, (emission, mdp.num_features, K)
        assert initial_skills(em, K) == skills and initial_skills(em, K, 2) == 2
        given = ModelConfig(emission=emission, max_skills=K, sampler=SamplerConfig(init_skills=2))
        assert default_moves(given, em).sampler.init_skills == 2
        assert ModelConfig.from_toml_string(cfg.to_toml()) == cfg  # the resolved value round-trips
    states = np.zeros((2, 4), np.int64)
    data = HMMData(states=states, actions=states, mask=np.ones((2, 4), bool))
    assert BPHMMKernel(make_emission("reward", onehot), data, max_skills=6).init_skills == 6
    assert BPHMMKernel(make_emission("reward", dom.mdp), data, max_skills=6).init_skills == 3
    assert BPHMMKernel(make_emission("reward", onehot), data, max_skills=6, init_skills=2).init_skills == 2


@pytest.mark.parametrize("text, message", [
    ('[prior]\nkappa = "abc"', "prior.kappa: expected a number, got 'abc'"),
    ("[sampler]\nchainz = 3", "sampler.chainz: unknown key"),
    ("[sampler]\nsamples = 2.5", "sampler.samples: expected an integer"),
    ("[sampler]\nwarmup = -1", "sampler.warmup: expected an integer >= 0"),
    ('[sampler]\nchain_method = "threaded"', "sampler.chain_method"),
    ("max_skills = 0", "max_skills: expected an integer >= 1"),
    ("[prior]\nalpha = 0.0", "prior.alpha: expected a positive number"),
    ("[prior.gamma]\nshape = 2.0", "prior.gamma: a hyperprior needs both shape and rate"),
    ("[prior]\nbeta = 1.0", "prior.beta: unknown key"),
    ("emission = 3", "emission: expected a table"),
    ("[emission]\nname = 3", "emission.name: expected a non-empty string"),
    ("[sampler]\ninit_skills = 9", "sampler.init_skills: 9 exceeds max_skills"),
    ("[sampler.moves]\nteleport = true", "teleport"),
    ("max_skills = [", "not valid TOML"),
])
def test_bad_toml_is_rejected_naming_the_key(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("(", r"\(")) as info:
        ModelConfig.from_toml(path)
    assert str(path) in str(info.value)


def test_python_configs_are_validated_too():
    with pytest.raises(ValueError, match="prior.kappa: expected a number"):
        PriorConfig(kappa="abc")
    with pytest.raises(ValueError, match="sampler.chains: expected an integer >= 1"):
        SamplerConfig(chains=0)
    with pytest.raises(ValueError, match="emission.options.f"):
        EmissionConfig("policy", {"f": object()})
    assert PriorConfig(kappa=0.0).kappa == Hyperparameter(0.0)  # no stickiness is allowed
    assert PriorConfig(alpha={"shape": 2.0, "rate": 4.0}).alpha == Hyperparameter(0.5, 2.0, 4.0)


# ------------------------------------------------------------------------------ fitting
@register_emission("toy_policy")
class ToyPolicy(PolicyEmission):
    """A user's emission: the conjugate policy emission under another name, with its own option."""

    def __init__(self, num_states, num_actions, concentration=0.5, note="toy"):
        super().__init__(num_states, num_actions, concentration)
        self.note = note

    def describe(self):
        return {**super().describe(), "note": self.note}


@pytest.fixture(scope="module", autouse=True)
def _unregister_toy():
    yield
    EMISSIONS.pop("toy_policy", None)


def small_problem(seed=0, N=3, T=20, S=4, A=3):
    rng = np.random.default_rng(seed)
    mdp = TabularMDP.from_dense(rng.dirichlet(np.ones(S), (S, A)))
    states = [rng.integers(0, S, T) for _ in range(N)]
    actions = [(np.arange(T) // 7 + i) % A for i in range(N)]  # skills that prefer one action each
    return mdp, Demonstrations(states, actions)


def test_a_registered_class_stands_for_its_name():
    assert EmissionConfig(ToyPolicy).name == "toy_policy"
    assert ModelConfig(emission=ToyPolicy).emission == EmissionConfig("toy_policy")

    class Unregistered(PolicyEmission):
        pass

    with pytest.raises(ValueError, match="emission.name: class Unregistered is not registered"):
        EmissionConfig(Unregistered)


TOY = ModelConfig(emission=EmissionConfig("toy_policy", {"concentration": 0.3, "note": "mine"}), max_skills=3,
                  sampler=SamplerConfig(chains=1, warmup=2, samples=4, init_window=5))


def test_a_registered_toy_emission_fits_through_the_config_by_name(tmp_path):
    mdp, demos = small_problem()
    path = tmp_path / "toy.toml"
    TOY.to_toml(path)
    result = fit(mdp, demos, path, progress_bar=False)
    assert result.emission == {"name": "toy_policy", "concentration": 0.3, "note": "mine"}
    # the run records the configuration it ran, with fit's default greedy merges and initial
    # skills (half of the 3 slots) filled in (and the switching model that "auto", the default, chose)
    ran = TOY.replace(sampler=dataclasses.replace(TOY.sampler, moves={"greedy_merge": 1, "greedy_split": 1,
                                                                   "greedy_from": 0.75}, init_skills=2),
                      prior=dataclasses.replace(TOY.prior, switching="sticky"))
    assert result.model_config == ran
    assert result.samples["policy"].shape == (1, 4, 3, 4, 3)
    # keyword arguments override the config (same model, so no new compilation)
    again = fit(mdp, demos, TOY, num_samples=6, seed=3, progress_bar=False)
    assert again.model_config == ran.replace(sampler=dataclasses.replace(ran.sampler, samples=6, seed=3))
    assert again.stats["log_joint"].shape == (1, 6)
    assert not np.array_equal(again.stats["log_joint"][:, :4], result.stats["log_joint"])


@pytest.mark.parametrize("change, message", [
    (dict(emission="no_such_emission"), "unknown emission 'no_such_emission'"),
    (dict(max_skills=0), "max_skills: expected an integer >= 1"),
    (dict(config={"sampler": {"chainz": 2}}), "sampler.chainz: unknown key"),
    (dict(config={"prior": {"kappa": "abc"}}), "prior.kappa: expected a number, got 'abc'"),
    (dict(emission_options={"concentration": 0.3, "colour": "red"}), "emission.options"),
    (dict(init_skills=5), "sampler.init_skills: 5 exceeds max_skills"),
    (dict(hyperpriors={"kappa": (1.0,)}), "prior.kappa: a hyperprior is"),
    (dict(moves={"birth_death": -1}), "sampler.moves.birth_death"),
    (dict(checkpoint_every=0), "sampler.checkpoint_every: expected an integer >= 1"),
    (dict(grow=1), "sampler.grow: expected true or false"),
    (dict(kappaa=1.0), "config: unknown option 'kappaa'"),
    (dict(init_segmentation=[np.zeros(20, int)] * 2), "init_segmentation has 2 trajectories, the demonstrations 3"),
    (dict(init_segmentation=[np.zeros(20, int)] * 2 + [np.zeros(19, int)]),
     r"init_segmentation\[2\] has shape \(19,\); trajectory 2 has 20 steps"),
    (dict(init_segmentation=[np.zeros(20)] * 2 + [np.r_[np.zeros(5), 0.5, np.zeros(14)]]),
     r"init_segmentation\[2\]\[5\] = 0.5 is not an integer"),
    (dict(init_segmentation=[np.arange(20) % 4] * 3), "uses 4 skills, more than max_skills = 3"),
    (dict(init_segmentation=5), "init_segmentation must be a sequence"),
])
def test_bad_input_is_a_value_error_before_compilation(no_compilation, change, message):
    mdp, demos = small_problem()
    kwargs = dict(config=TOY, progress_bar=False)
    kwargs.update(change)
    options = {k: kwargs.pop(k) for k in list(kwargs) if k in OPTIONS or k == "kappaa"}
    with pytest.raises(ValueError, match=message):
        fit(mdp, demos, resolve_config(kwargs.pop("config"), **options) if options else kwargs.pop("config"), **kwargs)


def test_demonstrations_outside_the_mdp_are_a_value_error_before_compilation(no_compilation):
    mdp, demos = small_problem()
    bad = Demonstrations([s for s in demos.states], [a for a in demos.actions[:2]] + [np.full(20, 3)])
    with pytest.raises(ValueError, match="trajectory 2, step 0: action 3"):
        fit(mdp, bad, TOY, progress_bar=False)


def test_fit_starts_from_a_given_segmentation(tmp_path):
    mdp, demos = small_problem()
    truth = [(np.arange(20) // 7 + i) % 3 for i in range(3)]  # the skill (preferred action) of each step
    labels = [7 * t - 2 for t in truth]  # any integers: relabelled in order of value
    result = fit(mdp, demos, TOY, num_warmup=0, num_samples=1, init_segmentation=labels, progress_bar=False)
    start = compiled_module.kept_compiled()[-1].kernel
    z0 = start.check_segmentation(labels)
    np.testing.assert_array_equal(z0[:, :20], np.stack(truth))
    # one sweep from the true segmentation keeps it (three well-separated action skills; a step
    # next to a switch may move, as one of the 60 does under seed 0)
    assert hungarian_accuracy(truth, result.segmentation) >= 0.95
    # the run records its start (relabelled), through a file too
    assert [r.tolist() for r in result.init_segmentation] == [t.tolist() for t in truth]
    assert "started from a given segmentation (3 skills)" in result.summary()
    result.save(tmp_path / "run.nc")
    assert load(tmp_path / "run.nc").equals(result)
    # a FitResult stands for its segmentation; the recorded start repeats the run bit for bit
    again = fit(mdp, demos, TOY, num_warmup=0, num_samples=1, init_segmentation=result, progress_bar=False)
    assert [r.tolist() for r in again.init_segmentation] == [r.tolist() for r in result.segmentation]
    assert hungarian_accuracy(truth, again.segmentation) >= 0.95
    repeat = fit(mdp, demos, result.model_config, init_segmentation=result.init_segmentation, progress_bar=False)
    # (the recorded configuration names the switching model "auto" chose: no choice to record again)
    assert result.switching["chosen"] == "sticky" and repeat.switching is None
    assert repeat.equals(dataclasses.replace(result, switching=None))
    default = fit(mdp, demos, TOY, num_warmup=0, num_samples=1, progress_bar=False)
    assert default.init_segmentation is None and "started from" not in default.summary()
    assert not default.equals(result)


def test_progress_in_a_log_shows_compiling_then_sweeps_with_an_eta(capsys):
    """Output that is not a terminal gets plain lines: the compiling first sweep named as such,
    then every tenth of the sweeps with the rate, the time left and the best chain's log joint
    after that sweep, then a closing line; no carriage returns."""
    mdp, demos = small_problem()
    result = fit(mdp, demos, TOY, num_samples=18, progress_bar=True)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("npbrs fit: ")]
    assert lines[0] == "npbrs fit: compiling the sampler (the first sweep); 20 sweeps to run"
    assert lines[1] == "npbrs fit: compiled; sweep 1/20 (warmup)"
    assert any(line.startswith("npbrs fit: sweep 2/20 (warmup), ") and "s per sweep, about" in line for line in lines)
    last = [line for line in lines if line.startswith("npbrs fit: sweep 20/20 (sample), ")]
    assert last and last[0].endswith(f", log joint {np.max(result.stats['log_joint'][:, -1]):.1f}"), last
    assert lines[-1].startswith("npbrs fit: done: 20 sweeps in ")
    assert len(lines) == 13 and "\r" not in err


def test_progress_counts_sweeps_of_every_chain_and_says_so():
    """A unit is a sweep of every chain, however the chains are swept; the first line says the
    sampler is compiling and what is counted, the closing line the sweeps each chain ran.
    (Checked to fail: a first line without the chains, a closing line of another count.)"""
    import io

    from npbrs.inference.driver.progress import Progress

    for chains, first in ((4, "; 10 sweeps of each of 4 chains to run"), (1, "; 10 sweeps to run")):
        out = io.StringIO()  # (not a terminal: plain lines)
        bar = Progress(10, 0, True, stream=out, chains=chains)
        for _ in range(10):
            bar.update(1)
        bar.close_done(10, 1.3)
        lines = out.getvalue().splitlines()
        assert lines[0] == "npbrs fit: compiling the sampler (the first sweep)" + first
        assert lines[1] == "npbrs fit: compiled; sweep 1/10 (compiling)"
        assert "about" in lines[-2] and "s left" in lines[-2]
        each = " of each of 4 chains" if chains == 4 else ""
        assert lines[-1] == f"npbrs fit: done: 10 sweeps{each} in 1.3 s", lines[-1]


def test_the_bar_s_clock_runs_from_the_start_and_its_time_left_from_the_second_sweep(monkeypatch):
    """In a terminal (tqdm): the elapsed time counts the compiling first sweep; the time left
    is timed from the sweeps after it. (Checked to fail with the clock restarted after the
    first sweep.)"""
    import io
    import time as clock

    from npbrs.inference.driver import progress

    now = [100.0]
    monkeypatch.setattr(progress, "interactive", lambda stream: True)
    monkeypatch.setattr(clock, "perf_counter", lambda: now[0])
    out = io.StringIO()
    bar = progress.Progress(11, 0, True, stream=out, chains=2)
    started = bar.bar.start_t
    now[0] += 30.0  # the first sweep compiles for 30 s
    bar.update(1)
    now[0] += 1.0  # then 1 s a sweep
    bar.update(1)
    bar.update(0)
    assert bar.bar.start_t == started  # (the clock was not restarted after compiling)
    assert bar.bar.format_dict["postfix"].startswith("about 9 s left")  # 9 sweeps left at 1 s each
    bar.close()


def test_the_warmup_sweeps_scalars_are_kept_saved_and_drawn(tmp_path):
    from npbrs.inference import load
    from npbrs.inference.analysis.plots import plot_trace
    from npbrs.inference.driver.results import LABEL_INVARIANT

    mdp, demos = small_problem()
    result = fit(mdp, demos, TOY, num_warmup=3, progress_bar=False)
    assert set(result.warmup_stats) == set(LABEL_INVARIANT)
    assert all(v.shape == (1, 3) and np.all(np.isfinite(v)) for v in result.warmup_stats.values())
    assert set(np.unique(result.warmup_stats["num_skills"])) <= {1, 2, 3}
    assert set(result.stats) >= set(LABEL_INVARIANT) and result.stats["log_joint"].shape == (1, 4)
    result.save(tmp_path / "run.nc")
    again = load(tmp_path / "run.nc")
    assert again.equals(result)
    plot_trace(again, tmp_path / "trace.png")
    assert (tmp_path / "trace.png").stat().st_size > 1000
