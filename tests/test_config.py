"""Training configs: presets, XML files, overrides, and rejection of unknown keys."""
import pytest

import dataclasses

from mi_grg.training.config import (FLAT_KEYS, PARTS, ConfigError, PRESETS, TrainConfig,
                                    make_config, read_config_xml, write_config_xml)


def test_paper_defaults():
    c = make_config("gr")
    assert (c.graph.k, c.deinit.sigma_d, c.graph.lambda_lap, c.densify.lambda_g,
            c.losses.lambda_ssim, c.losses.lambda_tv) == (6, 3.0, 8e-4, 1e-4, 0.25, 0.05)
    assert (c.optim.lr_position, c.optim.lr_density, c.optim.lr_scale,
            c.optim.lr_rotation) == (2e-4, 1e-2, 5e-3, 1e-3)
    assert c.densify.use_pga and c.graph.use_graph_field and c.deinit.n_points == 50000


def test_r2_preset_switches_every_graph_component_off():
    c = make_config("r2")
    assert not c.densify.use_pga and not c.graph.use_graph_field
    assert c.graph.lambda_lap == 0 and c.deinit.sigma_d == 0


def test_parts_have_unique_field_names_and_one_flat_mapping():
    """Every field lives in exactly one part, so a flat key (files, --option, records)
    names one field; from_flat and to_flat invert each other."""
    names = [f.name for cls in PARTS.values() for f in dataclasses.fields(cls)]
    assert len(names) == len(set(names)) == len(FLAT_KEYS) and set(names) == set(FLAT_KEYS)
    assert [f.name for f in dataclasses.fields(TrainConfig)] == list(PARTS)
    assert not set(PARTS) & set(FLAT_KEYS)           # no part shadows a flat key
    c = make_config("r2", k=5, lambda_tv=0.1, time_budget=60)
    flat = c.to_flat()
    assert list(flat) == list(FLAT_KEYS) and TrainConfig.from_flat(flat) == c
    assert (c.graph.k, c.losses.lambda_tv, c.run.time_budget) == (5, 0.1, 60.0)
    assert TrainConfig.from_flat({}) == TrainConfig() == make_config("gr")
    with pytest.raises(ConfigError, match="unknown training option 'lamda_tv'.*'lambda_tv'"):
        TrainConfig.from_flat({"lamda_tv": 0.1})
    with pytest.raises(ConfigError, match="must be >= 0: lambda_tv"):
        TrainConfig.from_flat({"lambda_tv": -1.0})


def test_file_round_trip_and_precedence(tmp_path):
    base = make_config("gr", k=7, lambda_tv=0.1, monitor_3d=True, keep_state="best")
    path = tmp_path / "cfg.xml"
    write_config_xml(base, path, method="gr")
    assert make_config("gr", path) == base
    # command-line override beats the file
    assert make_config("gr", path, k=5).graph.k == 5


@pytest.mark.parametrize("xml, match", [
    ('<training><integer name="kk" value="6"/></training>', "did you mean 'k'"),
    ('<training><float name="k" value="6"/></training>', "integer"),
    ('<training><integer name="k" value="6"/><integer name="k" value="7"/></training>', "twice"),
    ('<training><boolean name="use_pga" value="yes"/></training>', "bool"),
    ('<config><integer name="k" value="6"/></config>', "<training>"),
    ('<training colour="red"/>', "colour"),
    ('<training method="r2"/>', "not 'gr'"),
    ('<training><float name="lambda_tv" value="nan"/></training>', "finite"),
    ('<training><float name="lambda_tv" value="-1"/></training>', "lambda_tv"),
    ('<training><string name="keep_state" value="first"/></training>', "keep_state.*latest"),
    ('<training><string name="data_loss" value="l2"/></training>', "data_loss must be one of l1, rms"),
    ('<training><integer name="keep_state" value="1"/></training>', "string"),
    ('<training><float name="refine_fall" value="0"/></training>', "refine_fall must be a share"),
    ('<training><float name="refine_fall" value="1.5"/></training>', "refine_fall must be a share"),
    ('<training><float name="refine_tol" value="-0.01"/></training>', "must be >= 0: refine_tol"),
    ('<training><float name="refine_tol" value="1"/></training>', "refine_tol must be a share"),
    ('<training><float name="fit_rate_scale" value="0"/></training>', "fit_rate_scale must be"),
    ('<training><float name="fit_rate_scale" value="inf"/></training>', "fit_rate_scale|finite"),
])
def test_bad_files_name_the_problem(tmp_path, xml, match):
    path = tmp_path / "bad.xml"
    path.write_text(xml)
    with pytest.raises(ConfigError, match=match):
        make_config("gr", path)


def test_bad_overrides_and_methods():
    with pytest.raises(ConfigError, match="lambda_lap"):
        make_config("gr", lamda_lap=1.0)
    with pytest.raises(ConfigError, match="presets"):
        make_config("gr2")
    with pytest.raises(ConfigError, match="integer|int"):
        make_config("gr", k=2.5)
    with pytest.raises(ConfigError, match="keep_state expects a str"):
        make_config("gr", keep_state=1)


def test_shipped_configs_are_complete(tmp_path):
    import pathlib
    root = pathlib.Path(__file__).resolve().parents[1] / "scenes"
    for method in PRESETS:
        file_method, values = read_config_xml(root / f"{method}_default.xml")
        assert file_method == method
        assert set(values) == set(FLAT_KEYS)
        assert make_config(method, root / f"{method}_default.xml") == make_config(method)


def test_automatic_fields_are_none_in_files_options_and_records(tmp_path):
    """Fields chosen automatically are None: written as value="none", read from "none" (any
    case) or an omitted key, and from --option's JSON null or the string none. A 0, which
    older files used for "automatic", is an error that says what to write instead; configs
    recorded by earlier runs (checkpoints, metrics.json) read their 0 as None."""
    from mi_grg.training.checkpoint import upgrade_config_dict
    from mi_grg.training.config import AUTO_FIELDS
    c = make_config("gr")
    assert all(c.to_flat()[k] is None for k in AUTO_FIELDS if k != "tv_extent")
    assert c.losses.tv_extent == 3.0
    path = tmp_path / "c.xml"
    write_config_xml(make_config("gr", tv_extent="none", graph_s=0.5), path, method="gr")
    text = path.read_text()
    assert '<float name="tv_extent" value="none"/>' in text
    assert '<float name="graph_s" value="0.5"/>' in text
    back = make_config("gr", path)
    assert back.losses.tv_extent is None and back.graph.graph_s == 0.5 and back.schedule.iterations is None
    assert make_config("gr", graph_s=None).graph.graph_s is None
    assert make_config("gr", iterations="None").schedule.iterations is None
    old = tmp_path / "old.xml"
    old.write_text('<training><float name="graph_s" value="0.0"/></training>')
    with pytest.raises(ConfigError, match="graph_s must be > 0 or none.*write none"):
        make_config("gr", old)
    with pytest.raises(ConfigError, match="iterations must be > 0 or none"):
        make_config("gr", iterations=0)
    with pytest.raises(ConfigError, match="horizon must be > 0 or none"):
        make_config("gr", horizon=-5)
    with pytest.raises(ConfigError, match="k expects a int"):
        make_config("gr", k="none")                  # only automatic fields take none
    recorded = {**make_config("gr").to_flat(), "iterations": 0, "extent": 0.0,
                "graph_s": 0.0, "log_3d_every": 0, "sigma_d": 0.0}
    up = upgrade_config_dict(recorded)
    assert up == {**make_config("gr").to_flat(), "sigma_d": 0.0}   # sigma_d 0 is "off"
