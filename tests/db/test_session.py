"""db.session: one engine and one session factory per database URL, made again after a reset."""

from __future__ import annotations

from db.session import get_engine, get_sessionmaker, reset_engines


def test_a_url_keeps_one_session_factory_until_its_engine_is_replaced(tmp_path):
    url, other = f"sqlite:///{tmp_path / 'a.db'}", f"sqlite:///{tmp_path / 'b.db'}"
    try:
        first = get_sessionmaker(url)
        assert get_sessionmaker(url) is first and first.kw["bind"] is get_engine(url)
        assert get_sessionmaker(other) is not first
        reset_engines()
        again = get_sessionmaker(url)
        assert again is not first and again.kw["bind"] is get_engine(url)
    finally:
        reset_engines()
