"""`--version`, the licence files and CITATION.cff agree with pyproject.toml."""
import importlib.metadata
import tomllib
from pathlib import Path

import pytest

import plumbing as version_module
from datagen.cli import main as datagen_main
from gns.cli import main as gns_main

ROOT = Path(__file__).resolve().parent.parent
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


@pytest.mark.parametrize("main", [gns_main, datagen_main], ids=["gns", "datagen"])
def test_version_flag_prints_the_project_version(main, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out == f"rigid-gns {PROJECT['version']}\n"


def test_an_installed_copy_reports_its_metadata_and_an_unknown_one_says_so(tmp_path, monkeypatch):
    monkeypatch.setattr(version_module, "PYPROJECT", tmp_path / "pyproject.toml")   # not a checkout
    monkeypatch.setattr(importlib.metadata, "version", lambda name: "9.8.7")
    assert version_module.version_line() == "rigid-gns 9.8.7"
    (tmp_path / "pyproject.toml").write_text('[project]\nname = "someone-else"\nversion = "1.0"\n')
    assert version_module.version() == "9.8.7"   # another project's pyproject is not ours

    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)
    monkeypatch.setattr(importlib.metadata, "version", missing)
    assert version_module.version() == "unknown"


def test_licence_is_apache_and_names_the_contactnets_data_licence():
    text = (ROOT / "LICENSE").read_text()
    assert text.lstrip().startswith("Apache License") and "Version 2.0, January 2004" in text
    assert PROJECT["license"]["text"] == "Apache-2.0"
    bsd = ROOT / "LICENSES" / "contactnets-BSD-3-Clause.txt"
    assert "LICENSES/contactnets-BSD-3-Clause.txt" in text and "tests/data/contactnets/" in text
    assert bsd.read_text() == (ROOT / "tests" / "data" / "contactnets" / "LICENSE").read_text()
    assert bsd.read_text().startswith("BSD 3-Clause License")


def test_citation_file_matches_the_release_and_cites_the_paper():
    yaml = pytest.importorskip("yaml")
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["type"] == "software"
    assert str(cff["version"]) == PROJECT["version"] and cff["license"] == PROJECT["license"]["text"]
    paper = cff["references"][0]
    assert paper["title"] == "Graph network simulators can learn discontinuous, rigid contact dynamics"
    assert paper["authors"][0]["family-names"] == "Allen" and "CoRL 2022" in paper["conference"]["name"]


def test_datasets_record_the_release_they_were_made_by():
    import datagen
    assert datagen.__version__ == PROJECT["version"]
