"""The CI guard of test/conftest.py: a missing optional module skips locally and fails in CI."""
import pytest

from conftest import import_or_skip, in_ci


def test_missing_module_skips_locally(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    assert not in_ci()
    with pytest.raises(pytest.skip.Exception, match="not installed"):
        import_or_skip("uw_sil_no_such_module", reason="not installed")


@pytest.mark.parametrize("value", ["true", "True", "1"])
def test_missing_module_fails_in_ci(monkeypatch, value):
    monkeypatch.setenv("CI", value)
    assert in_ci()
    with pytest.raises(ImportError, match="CI=true but uw_sil_no_such_module cannot be imported"):
        import_or_skip("uw_sil_no_such_module", reason="not installed")


def test_present_module_is_returned_either_way(monkeypatch):
    import json

    for ci in ("", "true"):
        monkeypatch.setenv("CI", ci)
        assert import_or_skip("json", reason="stdlib") is json
