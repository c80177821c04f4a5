"""The test harness itself: real data beside the repository skips cleanly where absent, and never in CI."""

from __future__ import annotations

import pytest
from conftest import REQUIRE_SHARED_ENV, need_shared, shared_data


def test_missing_shared_data_skips_with_reason_and_fails_in_ci(tmp_path, monkeypatch):
    missing = tmp_path / "shared" / "data" / "nothing"
    monkeypatch.delenv(REQUIRE_SHARED_ENV, raising=False)
    with pytest.raises(pytest.skip.Exception, match=r"needs the real data .*absent here"):
        need_shared(missing)
    monkeypatch.setenv(REQUIRE_SHARED_ENV, "1")
    with pytest.raises(pytest.fail.Exception, match="CI must never skip"):
        need_shared(missing)
    assert need_shared(tmp_path) == tmp_path


def test_shared_data_is_here():
    """This environment has ../shared/data (a clone elsewhere skips the tests that need it)."""
    need_shared(shared_data() / "README.md")
