"""Scene files: the contract's sections and keys, defaults, overrides, and one clear error per mistake."""
import os
import re

import pytest

from dbf_hpc.errors import InputError
from dbf_hpc.scene import load_scene, parse_override, validate

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER = os.path.join(ROOT, "jobs", "paper_beam.toml")
BEAM = {"kind": "beam", "length": 1.0, "E": 117e9, "I": 8.78e-16, "A": 2.9e-7, "rho": 11800.0}


def scene(**sections):
    data = {"structure": dict(BEAM)}
    data.update(sections)
    return validate(data, "test.toml")


def test_paper_scene_holds_table_1():
    s = load_scene(PAPER)
    beam = s.beam()
    assert (beam.length, beam.E, beam.I, beam.A, beam.rho) == (1.0, 117e9, 8.78e-16, 2.9e-7, 11800.0)
    assert (beam.left, beam.right) == ("pinned", "pinned")
    (c,) = s.constraints
    assert c.x == 0.25 and c.law.kind == "deadband"
    assert c.law.clearance_minus == c.law.clearance_plus == 2.5e-3
    assert c.law.k_minus == c.law.k_plus == 1e6
    assert s["basis"]["modes"] == 6 and s["basis"]["dbf_stiffness"] == "auto"
    assert s["excitation"]["amplitude"] == 5e-3 and s["excitation"]["frequency_hz"] == 1.0


def test_overrides_change_values_with_toml_types():
    s = load_scene(PAPER, ["basis.modes=3", "constraint.clearance=1e-3", "structure.left=clamped",
                           "basis.dbf_stiffness=0.1"])
    assert s["basis"]["modes"] == 3 and s["basis"]["dbf_stiffness"] == 0.1
    assert s.constraints[0].law.clearance_plus == 1e-3
    assert s.beam().left == "clamped"
    assert parse_override("output.probes=[0.1, 0.2]") == ("output", "probes", [0.1, 0.2])


def test_defaults_fill_every_section():
    s = scene()
    assert s["basis"]["modes"] == 6 and s["excitation"]["kind"] == "none" and s.constraints == ()
    assert s["basis"]["enrichment"] == "dbf" and s.basis_settings().enrichment == "dbf"
    assert s.damping().kind == "none"


@pytest.mark.parametrize("data,message", [
    ({"struct": {}}, r"unknown section \[struct\]"),
    ({"basis": {"mode": 3}}, r"unknown key 'mode' in \[basis\]"),
    ({"basis": {"modes": "six"}}, "modes must be an integer"),
    ({"basis": {"modes": 2.5}}, "modes must be an integer"),
    ({"integrator": {"t_end": -1.0}}, "t_end must be positive"),
    ({"integrator": {"dt": 0}}, "dt must be positive"),
    ({"integrator": {"contact": "sometimes"}}, "contact must be"),
    ({"basis": {"modes": 4, "max_frequency_hz": 10.0}}, "not both"),
    ({"basis": {"dbf_stiffness": "soft"}}, "dbf_stiffness must be"),
    ({"basis": {"enrichment": "modal"}}, r'\[basis\]: enrichment must be one of "dbf", "static", "none", got \'modal\''),
    ({"constraint": [{"x": 1.5, "law": "deadband", "k": 1e6}]}, "not on the beam"),
    ({"constraint": [{"law": "deadband", "k": 1e6}]}, "x is required"),
    ({"constraint": [{"x": 0.25, "law": "deadband", "k": 1e6}, {"x": 0.25, "law": "linear", "k": 1.0}]},
     "constraints 1 and 2 are both at x = 0.25 m"),
    ({"constraint": [{"x": 0.25, "law": "stick", "k": 1e6}]}, r"\[\[constraint\]\] 1: law must be one of"),
    ({"output": {"probes": [-0.1]}}, "not on the beam"),
    ({"excitation": {"kind": "force", "frequency_hz": 1.0}}, "needs its position"),
    ({"excitation": {"kind": "quake"}}, "kind must be"),
    ({"damping": {"zeta": -0.01}}, "zeta"),
])
def test_bad_scenes_are_one_clear_error(data, message):
    with pytest.raises(InputError, match=message):
        scene(**data)


@pytest.mark.parametrize("structure,message", [
    ({"kind": "matrices", "stiffness": "K.mtx", "mass": "M.mtx", "supports": [0]},
     "supports applies to kind = \"beam\" and would be ignored here; apply a matrix model's supports to K and M"),
    ({"kind": "matrices", "stiffness": "K.mtx", "mass": "M.mtx", "left": "free"}, "left applies to kind = \"beam\""),
    ({"kind": "matrices", "stiffness": "K.mtx", "mass": "M.mtx", "E": 2e11}, "E applies to kind = \"beam\""),
    ({**BEAM, "influence": "r.npy"}, "influence applies to kind = \"matrices\" and would be ignored here"),
])
def test_a_key_of_the_other_kind_of_structure_is_refused(structure, message):
    # Red team: supports = [0] on a matrix model (a DOF the user meant to pin), or a beam's left end,
    # were accepted and ignored: the run was of a structure other than the scene says.
    with pytest.raises(InputError, match=message):
        validate({"structure": structure}, "test.toml")
    validate({"structure": {"kind": "matrices", "stiffness": "K.mtx", "mass": "M.mtx", "left": "pinned"}})  # default


def test_the_moving_end_of_a_matrix_model_is_refused_as_its_influence_vector_says_it():
    # Red team: end = "right" was accepted and ignored (r decides which support moves).
    structure = {"kind": "matrices", "stiffness": "K.mtx", "mass": "M.mtx", "influence": "r.npy"}
    base = {"kind": "base", "amplitude": 1e-3, "frequency_hz": 5.0}
    with pytest.raises(InputError, match="end applies to a beam and would be ignored here"):
        validate({"structure": structure, "excitation": {**base, "end": "right"}}, "test.toml")
    assert validate({"structure": structure, "excitation": base}).excitation().amplitude == 1e-3


@pytest.mark.parametrize("excitation,message", [
    ({"kind": "base", "x": 0.5}, "x applies to a force on a beam and would be ignored by kind = 'base'"),
    ({"kind": "force", "x": 0.5, "end": "right"}, "end applies to base excitation of a beam and would be ignored"),
    ({"kind": "force", "dof": 3}, "dof applies to a force on a matrices structure and would be ignored"),
    ({"kind": "random", "psd": 1.0, "band": [0.0, 10.0], "x": 0.5}, "x applies to a force on a beam"),
])
def test_where_a_load_acts_given_to_a_load_that_does_not_take_it_is_refused(excitation, message):
    # Red team: a base excitation with x = 0.5 m moved the left support (x read nowhere), and a force
    # with end = "right" acted at its x: the run was of another load than the scene says.
    harmonic = {"amplitude": 1e-3, "frequency_hz": 5.0} if excitation["kind"] != "random" else {}
    with pytest.raises(InputError, match=message):
        validate({"structure": BEAM, "excitation": {**harmonic, **excitation}}, "test.toml")
    kept = {**harmonic, **excitation, "kind": "none"}   # free vibration keeps every key (--set excitation.kind=none)
    assert validate({"structure": BEAM, "excitation": kept}).excitation().kind == "none"
    force = {"kind": "force", "x": 0.5, "amplitude": 1e-3, "frequency_hz": 5.0}
    assert validate({"structure": BEAM, "excitation": force}).excitation().x == 0.5


@pytest.mark.parametrize("key,value", [("span", [-1.0, 5.0]), ("span", [0.2, 0.4]), ("components", -1),
                                       ("components", 64), ("seed", 7)])
def test_a_random_loads_keys_on_a_harmonic_load_are_refused_by_name(key, value):
    # Red team: a base excitation with span = [-1, 5] m (off the beam) or components = -1 ran without a
    # word: a harmonic load has no loaded span, cosines or seed, the value described a load not applied.
    base = {"kind": "base", "amplitude": 1e-3, "frequency_hz": 5.0}
    with pytest.raises(InputError, match=rf"^test.toml: \[excitation\]: {key} has no meaning for kind = 'base' and "
                                         r"would be ignored: remove it"):
        validate({"structure": BEAM, "excitation": {**base, key: value}}, "test.toml")
    assert validate({"structure": BEAM, "excitation": {**base, key: value, "kind": "none"}}).excitation().kind == "none"
    if key != "span" or value[0] >= 0:   # the random load that takes it
        random = {"kind": "random", "psd": 1.0, "band": [0.0, 10.0], key: value}
        if key == "components" and value < 1:
            with pytest.raises(InputError, match="components must be at least 1"):
                validate({"structure": BEAM, "excitation": random}, "test.toml")
        else:
            taken = getattr(validate({"structure": BEAM, "excitation": random}).excitation(), key)
            assert taken == (tuple(value) if key == "span" else value)


@pytest.mark.parametrize("cache", ["", "  "])
def test_an_empty_basis_cache_directory_is_refused_not_taken_as_the_scenes_folder(cache):
    # Red team: cache = "" resolved to the scene file's folder, and the run wrote its basis-*.h5 among
    # the job files.
    with pytest.raises(InputError, match=r'^test.toml: \[basis\]: cache must be a directory or "off", got'):
        scene(basis={"cache": cache})
    assert scene(basis={"cache": "off"}).cache_dir() is None
    assert scene(basis={"cache": "bases"}).cache_dir() == os.path.join(os.getcwd(), "bases")


@pytest.mark.parametrize("section, key", [("output", "file"), ("basis", "cache"), ("structure", "stiffness")])
def test_a_name_holding_a_nul_character_is_refused_naming_its_key(section, key):
    # Red team: output.file = "a\u0000b.h5" (TOML allows the escape) ended in "internal error (ValueError):
    # embedded null byte"; no file name can hold one
    values = {"kind": "matrices", "stiffness": "K\x00.bin", "mass": "M.bin"} if section == "structure" else \
        {key: "a\x00b"}
    with pytest.raises(InputError, match=rf"^test.toml: \[{section}\]: {key} contains a NUL character, which no file "
                                         r"name or name may hold; remove it$"):
        scene(**{section: values})


@pytest.mark.parametrize("t_end", [5e-324, 2e-320])
def test_a_t_end_whose_default_sample_interval_is_zero_in_double_precision_is_refused_naming_t_end(t_end):
    # Red team: t_end = 5e-324 s (a denormal): its default sample_dt, t_end / 10000, is 0, and the run said
    # "IntegratorSettings sample_dt must be above 0, got 0.0" (a Python API class nobody named); from about
    # 2.5e-320 s the samples are not 0 (5e-324 s apart: such a run is refused later, by its step cap)
    with pytest.raises(InputError, match=r"^test.toml: \[integrator\] t_end = \S+ s: its default \[output\] sample_dt, "
                                         r"t_end / 10000, is 0 in double precision: give a longer t_end$"):
        scene(integrator={"t_end": t_end})
    assert scene(integrator={"t_end": 3e-320}).output().sample_dt > 0

@pytest.mark.parametrize("window", [1e-300, 1e-5])
def test_a_statistics_window_shorter_than_its_batch_means_need_is_refused_before_the_run(window):
    # Red team: estimate_statistics_window = 1e-300 s stopped the run after its integration ("IntegratorSettings
    # t_end must be above 0", a .partial and a checkpoint left); 1e-5 s (5 samples of 2 us) printed every
    # statistic's 95 % interval as "+- nan": batch means over 10 batches need 20 samples.
    with pytest.raises(InputError, match=r"^test.toml: \[basis\]: estimate_statistics_window = .* holds fewer than "
                                         r"the 20 samples \(sample_dt = 2e-06 s\) its intervals need: give at least "
                                         r"4e-05 s"):
        scene(integrator={"t_end": 0.02}, basis={"estimate_statistics_window": window})
    s = scene(integrator={"t_end": 0.02}, basis={"estimate_statistics_window": 4e-5})
    assert s.estimate_settings().statistics_window == 4e-5
    # a run shorter than 20 samples: its whole length is the window the default would take
    assert scene(integrator={"t_end": 0.02}, output={"sample_dt": 0.01},
                 basis={"estimate_statistics_window": 0.02}).estimate_settings().statistics_window == 0.02


@pytest.mark.parametrize("damping", [{"zeta": 0.02}, {"rayleigh_alpha": 1.0}, {"rayleigh_beta": 1e-4}])
def test_a_damping_matrix_beside_modal_or_rayleigh_damping_is_refused(damping):
    # Red team: the reduced and full-order models used the matrix and dropped zeta (or alpha, beta)
    # without a word, so a run had less damping than the scene says.
    with pytest.raises(InputError, match="a damping matrix .* and modal or Rayleigh damping .* were both given"):
        validate({"structure": {"kind": "matrices", "stiffness": "K.mtx", "mass": "M.mtx", "damping": "C.mtx"},
                  "damping": damping}, "test.toml")
    s = validate({"structure": {"kind": "matrices", "stiffness": "K.mtx", "mass": "M.mtx", "damping": "C.mtx"}})
    assert s.damping().kind == "none" and s.structure().damping.endswith("C.mtx")


@pytest.mark.parametrize("change,message", [({"E": -1.0}, "E must be positive"), ({"rho": None}, "rho is required"),
                                            ({"left": "glued"}, "left must be one of"),
                                            ({"kind": "shell"}, "kind must be")])
def test_bad_structures_are_one_clear_error(change, message):
    structure = {**BEAM, **change}
    if change.get("rho", 0) is None:
        del structure["rho"]
    with pytest.raises(InputError, match=message):
        validate({"structure": structure}, "test.toml")


@pytest.mark.parametrize("key", ["stiffness", "mass"])
@pytest.mark.parametrize("empty", ["", " "])
def test_an_empty_matrix_file_path_is_refused_as_missing(key, empty):
    # Red team: stiffness = "" passed validation (only None was missing) and the run ended in an internal
    # TypeError (the path became None)
    structure = {"kind": "matrices", "stiffness": "K.mtx", "mass": "M.mtx", key: empty}
    with pytest.raises(InputError, match=rf'^test.toml: \[structure\]: {key} \(a matrix file\) is required for kind = '
                                         rf'"matrices", got {empty!r}$'):
        validate({"structure": structure}, "test.toml")


@pytest.mark.parametrize("text,item,message", [
    ("[[basis]]\nmodes = 3\n", "basis.modes=4", r"\[basis\] must be a table$"),
    ("basis = 3\n", "basis.modes=4", r"\[basis\] must be a table$"),
    ("[constraint]\nx = 0.25\nk = 1e6\n", "constraint.k=2e6", r"constraints are written \[\[constraint\]\]"),
    ("constraint = [1, 2]\n", "constraint.1.k=2e6", r"\[\[constraint\]\] 1 must be a table$"),
])
def test_a_set_on_a_section_the_file_did_not_write_as_a_table_is_one_clear_error(tmp_path, text, item, message):
    # Red team: [[basis]] (an array of tables) with --set basis.modes=4 was an internal TypeError, and
    # [constraint] (one table) with --set constraint.k an internal AttributeError; without the --set
    # both were already one line.
    path = tmp_path / "s.toml"
    path.write_text(text + "[structure]\nlength = 1.0\nE = 117e9\nI = 8.78e-16\nA = 2.9e-7\nrho = 11800.0\n")
    for sets in ([item], []):
        with pytest.raises(InputError, match=f"^{path}: {message}"):
            load_scene(str(path), sets)


@pytest.mark.parametrize("change,message", [
    ({"length": 1e308}, r"beam E, I, A, rho, length, elements .* give omega\^2 of 0 to 0 1/s\^2"),
    ({"length": 1e30}, r"beam E, I, A, rho, length, elements .* give omega\^2 of .* outside the 1e-100 to 1e\+100"),
    ({"supports": [1.0]}, r"intermediate support at x = 1.0 m is not inside the beam \(0, 1.0\)"),
])
def test_the_beams_own_refusal_comes_first_naming_the_structure_section(change, message):
    # Red team: length = 1e308 m on the steam-generator tube said "constraints 1 and 2 are both at x = 1.5 m"
    # (0.75 and 1.5 m are one point within 1e-9 of the length), and 2**70 m "constraint at x = 0.25 m acts on a
    # fixed DOF"; the beam's numbers were checked only after the positions on it
    stops = [{"x": 0.25, "law": "deadband", "k": 1e6, "clearance": 1e-3},
             {"x": 0.5, "law": "deadband", "k": 1e6, "clearance": 1e-3}]
    with pytest.raises(InputError, match=rf"^test.toml: \[structure\]: {message}"):
        validate({"structure": {**BEAM, **change}, "constraint": stops}, "test.toml")
    # a beam within double precision, so long that 0.25 m and 0.5 m are one node of its mesh: said so
    with pytest.raises(InputError, match=r"^test.toml: constraints 1 and 2 at x = 0.25 m and x = 0.5 m are one point "
                                         r"of the mesh \(closer than 1e-09 of its length\); remove one"):
        validate({"structure": {**BEAM, "length": 2.0**70}, "constraint": stops}, "test.toml")


def test_matrices_structure_uses_dofs_and_needs_its_files():
    with pytest.raises(InputError, match="stiffness .* is required"):
        validate({"structure": {"kind": "matrices"}}, "t.toml")
    s = validate({"structure": {"kind": "matrices", "stiffness": "K.mtx", "mass": "M.mtx"},
                  "constraint": [{"dof": 3, "law": "linear", "k": 10.0}]}, "/some/where/t.toml")
    assert s.constraints[0].dof == 3 and s.resolve("K.mtx") == "/some/where/K.mtx"
    with pytest.raises(InputError, match="use dof, not x"):
        validate({"structure": {"kind": "matrices", "stiffness": "K", "mass": "M"},
                  "constraint": [{"x": 0.3, "law": "linear", "k": 1.0}]}, "t.toml")


@pytest.mark.parametrize("kind, said", [("fifo", "a named pipe"), ("directory", "a directory"),
                                         ("device", "a character device")])
def test_a_scene_that_is_no_regular_file_is_refused_saying_what_it_is_never_waited_on(shared_tmp_path, kind, said):
    # Red team: `dbf-hpc run FIFO` waited for a writer for ever (the scene's open); a directory said "Is a directory"
    from conftest import ends_a_hang, fifo_at
    from dbf_hpc.scene import load_scene_collective

    path = {"fifo": str(shared_tmp_path / "scene.toml"), "directory": str(shared_tmp_path), "device": "/dev/null"}[kind]
    if kind == "fifo":
        fifo_at(path)
    with ends_a_hang(60), pytest.raises(InputError, match=f"^cannot read scene {re.escape(repr(path))}: {said}, not a "
                                                          f"regular file$"):
        load_scene_collective(path)


def test_unreadable_or_malformed_files_are_errors(tmp_path):
    with pytest.raises(InputError, match="cannot read scene"):
        load_scene(str(tmp_path / "missing.toml"))
    bad = tmp_path / "bad.toml"
    bad.write_text("[structure\nkind = beam")
    with pytest.raises(InputError, match="not valid TOML"):
        load_scene(str(bad))
    with pytest.raises(InputError, match="expected section.key=value"):
        load_scene(PAPER, ["modes=3"])


def test_constraint_or_probe_on_a_support_is_an_error():
    on_support = {**BEAM, "supports": [0.5]}
    s = scene(structure=on_support, constraint=[{"x": 0.5, "law": "deadband", "k": 1e6, "clearance": 1e-3}])
    with pytest.raises(InputError, match="acts on a fixed DOF"):
        s.full_order_model()
    s = scene(structure=on_support, output={"probes": [0.5]})
    with pytest.raises(InputError, match="on a support"):
        s.full_order_model()


def test_the_scene_reference_in_docs_is_generated_from_the_schema_and_up_to_date():
    from dbf_hpc.laws import KEYS
    from dbf_hpc.schema import CONSTRAINT, SECTIONS, reference
    from dbf_hpc.scene import SCHEMA

    with open(os.path.join(ROOT, "docs", "scene.md")) as f:
        assert f.read() == reference(), "regenerate it: python -m dbf_hpc.schema > docs/scene.md"
    assert set(SCHEMA) == set(SECTIONS)
    documented = set(CONSTRAINT[1]) | {f"{k}_{side}" for k in ("clearance", "k", "exponent") for side in ("minus", "plus")}
    assert set(KEYS) <= documented, "every law key is documented"


def test_an_unknown_key_lists_the_valid_keys_of_its_section():
    with pytest.raises(InputError, match=r"unknown key 'K' in \[structure\] \(valid keys: kind, length, .*stiffness, mass"):
        scene(structure={**BEAM, "K": "K.mtx"})


def test_set_can_target_one_constraint_by_its_number():
    s = load_scene(os.path.join(ROOT, "jobs", "paper_beam_4.toml"), ["constraint.2.clearance=1e-3"])
    assert [c.law.clearance_plus for c in s.constraints][:3] == [s.constraints[0].law.clearance_plus, 1e-3,
                                                                 s.constraints[2].law.clearance_plus]
    assert s.constraints[0].law.clearance_plus != 1e-3
    with pytest.raises(InputError, match="constraint.N.key needs N from 1 to 4"):
        load_scene(os.path.join(ROOT, "jobs", "paper_beam_4.toml"), ["constraint.5.clearance=1e-3"])


def test_set_k_is_the_stiffness_on_both_sides_and_one_side_keeps_the_other():
    # New-user pass: README's `--set constraint.2.k=1e5` was refused on every paper-beam scene, whose
    # stops give k_minus and k_plus ("give either k or k_minus/k_plus, not both").
    path = os.path.join(ROOT, "jobs", "paper_beam_4.toml")
    s = load_scene(path, ["constraint.2.k=1e5"])
    assert (s.constraints[1].law.k_minus, s.constraints[1].law.k_plus) == (1e5, 1e5)
    assert s.constraints[0].law.k_plus == 1e6
    s = load_scene(path, ["constraint.k=2e5", "constraint.1.k_plus=3e5", "constraint.clearance_minus=1e-3"])
    assert [(c.law.k_minus, c.law.k_plus) for c in s.constraints[:2]] == [(2e5, 3e5), (2e5, 2e5)]
    assert s.constraints[0].law.clearance_minus == 1e-3 and s.constraints[0].law.clearance_plus == 2.5e-3
    s = load_scene(path, ["constraint.clearance=1e-3", "constraint.2.clearance_plus=4e-3"])
    assert [(c.law.clearance_minus, c.law.clearance_plus) for c in s.constraints[:2]] == [(1e-3, 1e-3), (1e-3, 4e-3)]
    # Red team: a side, then k, silently discarded the side (in a sweep, the case's label said otherwise)
    with pytest.raises(InputError, match="would discard the k_plus given before it"):
        load_scene(path, ["constraint.k_plus=1e5", "constraint.k=1e6"])


def test_set_k_on_sides_of_different_exponents_is_refused_as_it_would_carry_two_units():
    # Red team: on Eq. 42 (0.1 N/m^3 below, 1e6 N/m above) `--set constraint.k=1e6` made the cubic side
    # 1e6 N/m^3, with no word.
    path = os.path.join(ROOT, "jobs", "paper_beam_eq42.toml")
    with pytest.raises(InputError, match="exponents 3 and 1, so one k would be in N/m\\^3 below and N/m above"):
        load_scene(path, ["constraint.k=1e6"])
    for sets in (["constraint.exponent=1", "constraint.k=1e6"], ["constraint.k=1e6", "constraint.exponent=1"]):
        law = load_scene(path, sets).constraints[0].law
        assert (law.k_minus, law.k_plus, law.exponent_minus, law.exponent_plus) == (1e6, 1e6, 1.0, 1.0)
    law = load_scene(path, ["constraint.k=1e6", "constraint.k_minus=0.2"]).constraints[0].law
    assert (law.k_minus, law.k_plus) == (0.2, 1e6)


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_number_that_is_not_finite_is_refused(value):
    with pytest.raises(InputError, match="must be finite"):
        load_scene(PAPER, [f"excitation.amplitude={value}"])


def test_set_modes_replaces_the_scenes_max_frequency_and_the_other_way_round():
    # Red team: `--set basis.modes=4` on a scene choosing its modes by max_frequency_hz (the 2-D tube)
    # was refused ("give modes or max_frequency_hz, not both"), though --set overrides a scene value.
    tube = os.path.join(ROOT, "jobs", "steam_generator_tube_2d.toml")
    assert load_scene(tube)["basis"]["max_frequency_hz"] is not None
    s = load_scene(tube, ["basis.modes=4"])
    assert (s["basis"]["modes"], s["basis"]["max_frequency_hz"]) == (4, None)
    s = load_scene(PAPER, ["basis.max_frequency_hz=100.0"])
    assert (s["basis"]["modes"], s["basis"]["max_frequency_hz"]) == (None, 100.0)
    with pytest.raises(InputError, match="give modes or max_frequency_hz, not both"):
        load_scene(tube, ["basis.modes=4", "basis.max_frequency_hz=100.0"])


def test_a_tolerance_on_a_scene_choosing_its_modes_by_frequency_says_how_to_replace_it_from_the_command_line():
    # The shipped tubes set max_frequency_hz; "remove max_frequency_hz" left a --set user no way to do so
    # (--set cannot remove a key), while --set basis.modes replaces it.
    tube = os.path.join(ROOT, "jobs", "steam_generator_tube.toml")
    with pytest.raises(InputError, match=r"remove max_frequency_hz, or .*--set basis.modes=4 replaces it"):
        load_scene(tube, ["basis.tolerance=0.05"])
    s = load_scene(tube, ["basis.tolerance=0.05", "basis.modes=4"])
    assert (s["basis"]["modes"], s["basis"]["max_frequency_hz"], s["basis"]["tolerance"]) == (4, None, 0.05)


def test_every_rank_runs_the_scene_rank_0_read_also_when_another_rank_cannot_read_it(monkeypatch):
    # Each rank read the file itself: an edit while the job started, or a node that cannot read the
    # path, gave the ranks different scenes or one rank's error while the others went on
    from mpi4py import MPI

    from dbf_hpc import scene as scene_module

    comm = MPI.COMM_WORLD
    if comm.rank:
        monkeypatch.setattr(scene_module, "read_scene_bytes", lambda path: (_ for _ in ()).throw(
            InputError(f"cannot read scene {path!r}: No such file or directory")))
    scene = scene_module.load_scene_collective(PAPER, ["integrator.t_end=0.5"])
    assert comm.allgather(scene.text) == [scene.text] * comm.size and scene["integrator"]["t_end"] == 0.5
    with pytest.raises(InputError, match="cannot read scene"):     # rank 0's error is every rank's
        scene_module.load_scene_collective(os.path.join(ROOT, "jobs", "no_such_scene.toml"))


@pytest.mark.parametrize("kind, above", [("power", "N/m"), ("hertz", "N/m\\^1.5")])
def test_set_k_is_refused_when_a_side_of_another_exponent_takes_its_kinds_default(tmp_path, kind, above):
    # Red team: Eq. 42 written without exponent_plus (the power law's default 1) took `--set constraint.k=1e6`
    # as 1e6 N/m^3 below and 1e6 N/m above: the check read the missing exponent as unknown, not as 1 (1.5
    # for hertz), and let two units pass
    with open(os.path.join(ROOT, "jobs", "paper_beam_eq42.toml")) as f:
        text = f.read().replace("exponent_plus = 1.0\n", "").replace('law = "power"', f'law = "{kind}"')
    path = tmp_path / "eq42.toml"
    path.write_text(text)
    assert load_scene(str(path)).constraints[0].law.exponent_plus == (1.0 if kind == "power" else 1.5)
    with pytest.raises(InputError, match=f"so one k would be in N/m\\^3 below and {above} above"):
        load_scene(str(path), ["constraint.k=1e6"])
    law = load_scene(str(path), ["constraint.exponent=3", "constraint.k=1e6"]).constraints[0].law
    assert (law.k_minus, law.k_plus, law.exponent_minus, law.exponent_plus) == (1e6, 1e6, 3.0, 3.0)


@pytest.mark.parametrize("path", [None, 3, "", b"jobs/paper_beam.toml"])
def test_a_scene_path_that_is_not_a_path_is_one_input_error_and_no_file_descriptor_is_touched(path):
    # Red team: load_scene(None) raised a bare TypeError, and load_scene(3) opened file descriptor 3
    # (whatever the process had there), read it and closed it.
    had_fd_3 = path == 3 and _open_fd(3)
    with pytest.raises(InputError, match="load_scene: give the path of a scene file"):
        load_scene(path)
    if had_fd_3:
        assert _open_fd(3), "file descriptor 3 is still open"


def _open_fd(fd: int) -> bool:
    try:
        os.fstat(fd)
        return True
    except OSError:
        return False


def test_atol_help_says_it_is_in_modal_units_per_form_and_unused_by_the_full_order_reference():
    # The reduced model applies [integrator] atol unscaled to every state: q (m kg^(1/2)) and q' (m kg^(1/2)/s)
    # of the M-orthonormal second-order form, the A-orthonormal eta (J^(1/2)) of the state-space form; the
    # full-order reference takes fixed steps. On the pipe the q' part alone set the step count (229374 steps;
    # 5929 with it off, 229396 with q's off: docs/design.md), so the help must not read as a physical tolerance.
    from dbf_hpc.schema import SECTIONS

    help_ = SECTIONS["integrator"][1]["atol"].doc
    for words in ("not physical", "m kg^(1/2)/s", "atol / omega", "state_space", "J^(1/2)", "--method full does not use it"):
        assert words in help_, words


@pytest.mark.parametrize("sets, what", [
    (["excitation.amplitude=5"], r"\[excitation\]: amplitude = 5 m, the support's motion,"),
    (["excitation.amplitude=-1.5"], r"\[excitation\]: amplitude = -1.5 m, the support's motion,"),
    (["excitation.kind=none", "initial.amplitude=3"], r"\[initial\]: amplitude = 3 m, the peak initial displacement,"),
])
def test_a_displacement_longer_than_the_beam_is_refused_as_a_unit_slip(sets, what):
    # Red team: the paper beam's 5 mm support motion given as 5 (m), and a 3 m initial displacement of its
    # 1 m beam, ran to the end without a word: a linear beam model far outside its small deflections.
    with pytest.raises(InputError, match=rf"^{re.escape(PAPER)}: {what} is more than the beam's length \(1 m\): a "
                                         rf"linear \(small-deflection\) beam model cannot carry it; check its unit"):
        load_scene(PAPER, sets)
    # up to the length it is the user's to judge; the force's amplitude is in N, not checked
    assert load_scene(PAPER, ["excitation.amplitude=1.0"])["excitation"]["amplitude"] == 1.0
    assert load_scene(PAPER, ["excitation.kind=force", "excitation.x=0.5", "excitation.amplitude=50.0"])


@pytest.mark.parametrize("planes, initial, message", [
    (1, {"mode": 3}, r"mode = 3 is given without the amplitude it shapes: the structure would start at rest and "
                     r"mode be ignored; give amplitude \(m\), or remove mode$"),
    (2, {"mode": 2}, r"mode = 2 is given without the amplitude or velocity it shapes: .*give amplitude \(m\) or "
                     r"velocity \(m/s\), or remove mode$"),
    (2, {"mode": 2, "velocity": 0.1, "direction": [0.0, 1.0]}, r"direction = \[0.0, 1.0\] is given without the "
                                                                r"amplitude it shapes"),
    (2, {"amplitude": 1e-3, "velocity_direction": [1.0, 0.0]}, r"velocity_direction = \[1.0, 0.0\] is given "
                                                                r"without the velocity it shapes"),
])
def test_an_initial_shape_given_without_the_motion_it_shapes_is_refused_naming_the_key(planes, initial, message):
    # Red team: [initial] mode = 3 without amplitude ran the structure at rest without a word.
    with pytest.raises(InputError, match=r"^test.toml: \[initial\]: " + message):
        validate({"structure": {**BEAM, "planes": planes}, "initial": initial}, "test.toml")
    # with the motion it shapes given, also as 0 (a case at rest, a --set turning it off), it is kept
    moved = {key: 0.0 for key in ("amplitude", "velocity") if planes == 2 or key == "amplitude"}
    assert validate({"structure": {**BEAM, "planes": planes}, "initial": {**moved, **initial}})["initial"] == \
        {**SCENE_INITIAL, **moved, **initial}
    assert load_scene(PAPER, ["initial.mode=3", "initial.amplitude=0"])["initial"]["mode"] == 3


SCENE_INITIAL = {"mode": 1, "amplitude": 0.0, "direction": [], "velocity": 0.0, "velocity_direction": []}


@pytest.mark.parametrize("sets, message", [
    (["constraint.clearance=2.5"], r"clearance = 2.5 m is more than the beam's length \(1 m\): a linear "
                                   r"\(small-deflection\) beam never reaches that stop; check its unit \(m: 2.5 mm is "
                                   r"2.5e-3\)$"),
    (["constraint.clearance_plus=1.5"], r"clearance_plus = 1.5 m is more than the beam's length \(1 m\).*, or set "
                                        r"k_plus = 0 for a side without a stop$"),
    (["structure.length=2e-3", "constraint.x=5e-4", "output.probes=[1e-3]", "excitation.amplitude=1e-3"],
     r"clearance = 0.0025 m is more than the beam's length \(0.002 m\)"),
])
def test_a_stop_farther_than_the_beams_length_is_refused_as_a_unit_slip(sets, message):
    # Red team: the paper beam's 2.5 mm clearance given as 2.5 (m) ran to the end and only then warned that the
    # stop was never reached: a linear beam's motion stays far below its length, as a support motion or initial
    # displacement longer than the beam is refused (test_a_displacement_longer_than_the_beam_is_refused_...).
    with pytest.raises(InputError, match=rf"^{re.escape(PAPER)}: \[\[constraint\]\] 1: {message}"):
        load_scene(PAPER, sets)
    # up to the length it is the user's to judge, and a side without a stop (k = 0) has no reach
    assert load_scene(PAPER, ["constraint.clearance=1.0"]).constraints[0].law.clearance_plus == 1.0
    assert load_scene(PAPER, ["constraint.clearance_minus=5.0", "constraint.k_minus=0.0"]).constraints[0].law.k_plus == 1e6
    tube = {"structure": {**BEAM, "planes": 2}, "constraint": [{"x": 0.3, "law": "circular", "clearance": 2.0, "k": 1e6}]}
    with pytest.raises(InputError, match=r"\[\[constraint\]\] 1: clearance = 2 m is more than the beam's length"):
        validate(tube)


@pytest.mark.parametrize("data,message", [
    ({"t_end": 1.0}, r"^test.toml: 't_end' is outside any section \(above the first \[section\] line\); move it under "
                     r"\[integrator\] \(sections: "),
    ({"amplitude": 1e-3}, r"'amplitude' is outside any section .* move it under \[excitation\] or \[initial\] "),
    ({"clearance": 1e-3}, r"'clearance' is outside any section .* move it under \[\[constraint\]\] "),
    ({"scene": "paper_beam.toml", "axes": {"excitation.frequency_hz": [1.0, 1.1]}},
     r"^test.toml: is a sweep file \(a base scene and its axes or cases\), not a scene: run it with dbf-hpc sweep "
     r"test.toml$"),
])
def test_a_key_above_every_section_or_a_sweep_file_run_as_a_scene_is_named_as_such(data, message):
    # New-user pass: t_end = 1.0 written above [structure] (TOML puts it at the top level) and `dbf-hpc run`
    # of a sweep file (its top-level scene = "...") were both "unknown section [t_end]" / "[scene]".
    with pytest.raises(InputError, match=message):
        scene(**data)


def test_a_scene_path_that_does_not_exist_names_the_directory_it_was_looked_for_in(tmp_path, monkeypatch):
    # New-user pass: `dbf-hpc run jobs/paper_beam.toml` from inside jobs/ said only "No such file or directory".
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match=rf"^cannot read scene 'jobs/paper_beam.toml': No such file or directory "
                                         rf"\(relative to the current directory {re.escape(str(tmp_path))}\)$"):
        load_scene("jobs/paper_beam.toml")
    with pytest.raises(InputError, match=r"^cannot read scene '/no/such/scene.toml': No such file or directory$"):
        load_scene("/no/such/scene.toml")   # an absolute path says all there is


@pytest.mark.parametrize("item,message", [
    ("t_end=1", r"^--set 't_end=1': expected section.key=value, here --set integrator.t_end=1$"),
    ("amplitude=1e-3", r"here --set excitation.amplitude=1e-3 or --set initial.amplitude=1e-3$"),
    ("k = 1e5", r"here --set constraint.k=1e5$"),
    ("nonsense=1", r"^--set 'nonsense=1': expected section.key=value$"),
])
def test_a_set_without_its_section_names_the_section_that_has_the_key(item, message):
    # New-user pass: --set t_end=1 said only "expected section.key=value".
    with pytest.raises(InputError, match=message):
        parse_override(item)


@pytest.mark.parametrize("data,message", [
    ({"integrator": {"modes": 10}}, r"unknown key 'modes' in \[integrator\] \(valid keys: .*\); modes is a key of "
                                    r"\[basis\]$"),
    ({"structure": {**BEAM, "clearance": 1e-3}}, r"unknown key 'clearance' in \[structure\] .*; clearance is a key of "
                                                 r"\[\[constraint\]\]$"),
    ({"basis": {"mode": 3}}, r"unknown key 'mode' in \[basis\] .*; did you mean 'modes'\?$"),
    ({"integrator": {"tend": 1.0}}, r"; did you mean 't_end'\?$"),
    ({"constraint": [{"x": 0.25, "clearence": 1e-3, "k": 1e6}]}, r"unknown key 'clearence' .*; did you mean "
                                                                 r"'clearance'\?$"),
    ({"integrator": {"zzz": 1.0}}, r"unknown key 'zzz' in \[integrator\] \(valid keys: [^;]*\)$"),
])
def test_an_unknown_key_names_its_near_miss_or_the_section_that_has_it(data, message):
    # New-user pass: modes under [integrator] and a misspelt key got only the section's list of keys.
    with pytest.raises(InputError, match=message):
        scene(**data)
