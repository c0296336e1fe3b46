"""The products choice (pipeline.ingest.products): the command line's and session.yaml's
keys, checked strictly, and the command line over session.yaml key by key."""

from __future__ import annotations

from pathlib import Path

import pytest

from mscal_core.errors import InputError, SessionError
from pipeline.ingest.products import Products, cli_choice, resolve, yaml_choice
from pipeline.ingest.session import load_session
from pipeline.run.card import load_card_settings
from pipeline.run.cli import main

FIELD_YAML = """camera: ximea-mq022hg-sm5x5-nir
reflector: {reflectance: 0.5, size_m: [0.5, 0.5]}
marker: {dictionary: DICT_4X4_50, id: 3, size_m: 0.1}
"""


def test_default_products_are_the_survey_set() -> None:
    assert resolve().record() == {"radiance": False, "indices": ["ndvi"], "tiffs": True, "keep_flagged": False,
                                  "shoulder_bound": 0.03}
    assert resolve() == Products()


def test_command_line_choice() -> None:
    assert cli_choice() == {}
    assert cli_choice("radiance", "ndre", False) == {"radiance": True, "indices": ["ndvi", "ndre"], "tiffs": False}
    assert cli_choice("none", "none", True) == {"radiance": False, "indices": ["ndvi"], "tiffs": True}
    assert cli_choice(indices="ndre,ndvi,ndre") == {"indices": ["ndvi", "ndre"]}  # NDVI first, each once
    assert cli_choice(keep_flagged=True, shoulder_bound=0.05) == {"keep_flagged": True, "shoulder_bound": 0.05}
    assert cli_choice(keep_flagged=False) == {}  # the flag's absence is no choice: session.yaml's stands
    with pytest.raises(InputError, match=r"--shoulder-bound -0.1: must be positive"):
        cli_choice(shoulder_bound=-0.1)
    with pytest.raises(InputError, match=r"--products 'ndre': not an opt-in product \(opt-in products: radiance"):
        cli_choice("ndre")
    with pytest.raises(InputError, match=r"--indices: no index 'gndvi' in catalogs/indices \(available: ndre, ndvi;"):
        cli_choice(indices="ndre,gndvi")


def test_yaml_choice_is_strict(tmp_path) -> None:
    path = tmp_path / "session.yaml"
    assert yaml_choice(None, path) == {}
    assert yaml_choice({"tiffs": False}, path) == {"tiffs": False}
    assert yaml_choice({"radiance": True, "indices": ["ndre"]}, path) == {"radiance": True,
                                                                           "indices": ["ndvi", "ndre"]}
    assert yaml_choice({"keep_flagged": True, "shoulder_bound": 0.05}, path) == {"keep_flagged": True,
                                                                                  "shoulder_bound": 0.05}
    keys = "radiance, indices, tiffs, keep_flagged, shoulder_bound"
    bad = [({"extra": ["radiance"]}, f"products: unknown key(s) extra (allowed keys: {keys})"),
           ({"keep_flagged": "yes"}, "products.keep_flagged must be true or false, got 'yes'"),
           ({"shoulder_bound": 0}, "products.shoulder_bound must be a positive number, got 0"),
           ({"tiffs": "no"}, "products.tiffs must be true or false, got 'no'"),
           ({"radiance": 1}, "products.radiance must be true or false, got 1"),
           ({"indices": "ndre"}, "products.indices must be a list of index names, got 'ndre'"),
           ({"indices": ["gndvi"]}, "products.indices: no index 'gndvi' in catalogs/indices"),
           (["radiance"], f"products must be a mapping of {keys}")]
    for value, message in bad:
        with pytest.raises(SessionError) as err:
            yaml_choice(value, path)
        assert str(err.value).startswith(f"{path}: {message}") and "\n" not in str(err.value)


def test_command_line_wins_over_session_yaml_key_by_key() -> None:
    yaml = {"radiance": True, "indices": ["ndvi", "ndre"], "tiffs": False}
    assert resolve(yaml, {}).record() == {**yaml, "keep_flagged": False, "shoulder_bound": 0.03}
    assert resolve(yaml, {"tiffs": True}).record() == {"radiance": True, "indices": ["ndvi", "ndre"], "tiffs": True,
                                                       "keep_flagged": False, "shoulder_bound": 0.03}
    assert resolve({"keep_flagged": True, "shoulder_bound": 0.05}, {"shoulder_bound": 0.1}).record() == {
        "radiance": False, "indices": ["ndvi"], "tiffs": True, "keep_flagged": True, "shoulder_bound": 0.1}
    assert resolve(yaml, {"radiance": False, "indices": ["ndvi"]}).record() == {
        "radiance": False, "indices": ["ndvi"], "tiffs": False, "keep_flagged": False, "shoulder_bound": 0.03}


def _field_session(root: Path, products: str = "") -> Path:
    root.mkdir(parents=True)
    (root / "response").mkdir()
    (root / "session.yaml").write_text(FIELD_YAML + products)
    return root


def test_session_yaml_products_of_field_and_card_sessions(tmp_path) -> None:
    field = _field_session(tmp_path / "field", "products: {indices: [ndre], tiffs: false}\n")
    assert load_session(field).products == {"indices": ["ndvi", "ndre"], "tiffs": False}
    assert load_session(_field_session(tmp_path / "plain")).products == {}
    card = tmp_path / "card"
    card.mkdir()
    (card / "session.yaml").write_text("products:\n  radiance: true\n  tiffs: false\n")
    assert load_card_settings(card).products == {"radiance": True, "tiffs": False}
    (card / "session.yaml").write_text("products: {radiance: true, geotiff: true}\n")
    with pytest.raises(SessionError, match=r"products: unknown key\(s\) geotiff"):
        load_card_settings(card)
    bad = _field_session(tmp_path / "bad", "products: {tiff: false}\n")
    with pytest.raises(SessionError, match=r"session.yaml: products: unknown key\(s\) tiff \(allowed keys"):
        load_session(bad)


def test_run_and_serve_refuse_a_bad_choice_before_anything_runs(tmp_path, capsys) -> None:
    """One line on stderr, exit status 2, nothing written: radiance of a field session (Eq. 15
    has no radiance), an unknown index, an unknown product; session.yaml's own products too."""
    field = _field_session(tmp_path / "field")
    assert main(["run", str(field), "-o", str(tmp_path / "out"), "--products", "radiance"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--products radiance is for cameras with factory radiometry" in err and "a field session's" in err
    assert "\n" not in err and not (tmp_path / "out").exists()
    assert main(["run", str(field), "-o", str(tmp_path / "out"), "--indices", "gndvi"]) == 2
    assert "no index 'gndvi' in catalogs/indices (available: ndre, ndvi" in capsys.readouterr().err
    assert main(["serve", "--inbox", str(tmp_path), "-o", str(tmp_path / "served"), "--once",
                 "--products", "thermal"]) == 2
    assert "--products 'thermal': not an opt-in product" in capsys.readouterr().err
    yaml_radiance = _field_session(tmp_path / "yaml", "products: {radiance: true}\n")
    assert main(["run", str(yaml_radiance), "-o", str(tmp_path / "out2")]) == 2
    assert "--products radiance is for cameras with factory radiometry" in capsys.readouterr().err
    # the command line's choice wins: radiance off for this run
    from pipeline.run.runner import check_products

    assert check_products(yaml_radiance, {"radiance": False}).radiance is False
