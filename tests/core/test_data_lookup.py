"""Where the tests and `slamkit-data download test-data` look for the test data
(slamkit.downloads.excerpts): $SLAMKIT_DATA, the developers' shared folder beside the checkout,
the download's default folder in the project cache, the checkout's .cache/slamkit/test-data."""

from __future__ import annotations

from slamkit.downloads.excerpts import default_root, find_test_data


def test_the_lookup_order(tmp_path, monkeypatch):
    project = tmp_path / "clone"
    cache = tmp_path / "cache"
    monkeypatch.delenv("SLAMKIT_DATA", raising=False)
    monkeypatch.setenv("SLAMKIT_CACHE", str(cache))
    assert default_root() == cache / "test-data"
    assert find_test_data(project) == cache / "test-data"  # nothing there: where the download puts it
    (project / ".cache" / "slamkit" / "test-data").mkdir(parents=True)
    assert find_test_data(project) == project / ".cache" / "slamkit" / "test-data"
    (cache / "test-data").mkdir(parents=True)
    assert find_test_data(project) == cache / "test-data"
    (tmp_path / "shared" / "data").mkdir(parents=True)
    assert find_test_data(project) == tmp_path / "shared" / "data"
    assert find_test_data() == cache / "test-data"  # no checkout: the project cache only
    monkeypatch.setenv("SLAMKIT_DATA", str(tmp_path / "elsewhere"))
    assert find_test_data(project) == tmp_path / "elsewhere" and default_root() == tmp_path / "elsewhere"
