"""The synthetic-data cache key: it covers every source that shapes the generated files."""

import ast
import importlib.util
import shutil
from pathlib import Path

import pytest

import fcnpose_tf
from fcnpose_tf.data import synthcache

PACKAGE = Path(fcnpose_tf.__file__).resolve().parent


def _module_of(path: Path) -> str:
    rel = path.resolve().relative_to(PACKAGE.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _is_module(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:  # a name inside a module, not a submodule
        return False


def _first_party_imports(path: Path) -> set[str]:
    """fcnpose_tf modules a source file imports (at any depth of the file)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("fcnpose_tf"):
            for alias in node.names:  # `from fcnpose_tf import fileio` imports a module too
                name = f"{node.module}.{alias.name}"
                found.add(name if _is_module(name) else node.module)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("fcnpose_tf")}
    return found


def test_sources_are_the_synth_package_keypoints_and_the_via_writer():
    names = {p.resolve().relative_to(PACKAGE).as_posix() for p in synthcache.generator_sources()}
    synth_modules = {f"data/synth/{p.name}" for p in (PACKAGE / "data" / "synth").glob("*.py")}
    assert len(synth_modules) > 5 and synth_modules <= names
    assert {"keypoints.py", "data/via.py", "fileio.py"} <= names


def test_every_module_the_generator_imports_is_hashed_or_declared_harmless():
    """A new first-party import in the generator (or in what it imports) must be decided on."""
    hashed = {_module_of(p) for p in synthcache.generator_sources()}
    allowed = hashed | set(synthcache.NOT_SHAPING_MODULES)
    for source in synthcache.generator_sources():
        for module in _first_party_imports(source):
            assert module in allowed or any(module.startswith(h + ".") for h in hashed), (source, module)


def _copies(tmp_path):
    """The generator's sources copied under tmp_path, in the same layout."""
    copies = []
    for source in synthcache.generator_sources():
        target = tmp_path / source.resolve().relative_to(PACKAGE)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, target)
        copies.append(target)
    return copies


@pytest.mark.parametrize("edited", ["keypoints.py", "data/via.py", "fileio.py", "data/synth/frame.py",
                                    "data/synth/kinematics.py"])
def test_an_edit_in_any_source_changes_the_fingerprint(tmp_path, monkeypatch, edited):
    copies = _copies(tmp_path)
    monkeypatch.setattr(synthcache, "generator_sources", lambda: copies)
    before = synthcache.generator_fingerprint()
    assert synthcache.generator_fingerprint() == before  # stable
    target = tmp_path / edited
    target.write_bytes(target.read_bytes() + b"#")
    assert synthcache.generator_fingerprint() != before


def test_default_fingerprint_hashes_the_installed_sources():
    assert synthcache.generator_fingerprint() == synthcache.generator_fingerprint(synthcache.generator_sources())
    assert len(synthcache.generator_fingerprint()) == 12


def test_a_set_another_process_cached_first_is_taken_not_an_error(tmp_path, monkeypatch):
    """Two compress runs started together both generate the default set; the second to finish finds the folder
    in place (rename: directory not empty) and uses it."""
    from fcnpose_tf.data import synth

    monkeypatch.setenv("FCNPOSE_CACHE", str(tmp_path))
    real_generate = synth.generate

    def generate_while_another_finishes(out, **kwargs):
        real_generate(out, **kwargs)
        other = synthcache.cache_dir() / f"synth-{synthcache.generator_fingerprint()}" / "ur5_n2_seed5_64x48"
        real_generate(other, **kwargs)  # the other process's rename lands first

    monkeypatch.setattr(synth, "generate", generate_while_another_finishes)
    folder = synthcache.synthetic_dataset(2, 5, 64, 48)
    assert (folder / "ur5_synth.json").is_file()
    assert sorted(p.name for p in folder.parent.iterdir()) == ["ur5_n2_seed5_64x48"]  # our copy is gone
