"""Compiled templates kept between runs (masking_lab.formats.template_cache), on real folders."""

from __future__ import annotations

import os
import tempfile

import jinja2
import pytest

from masking_lab.formats import html_report
from masking_lab.formats.template_cache import compiled_template_cache

PAGE = "{% for x in items %}<li>{{ x }}</li>{% endfor %}"


def environment(templates, cache_dir):
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(templates)),
        autoescape=True,
        bytecode_cache=compiled_template_cache(str(cache_dir)),
    )


def never_compiles(env):
    def compile_(*args, **kwargs):
        raise AssertionError("compiled although a compiled copy was kept")

    env.compile = compile_
    return env


def counting(env):
    calls = []
    compile_ = env.compile

    def counted(*args, **kwargs):
        calls.append(args[1] if len(args) > 1 else kwargs.get("name"))
        return compile_(*args, **kwargs)

    env.compile = counted
    return env, calls


@pytest.fixture
def folders(tmp_path):
    templates, cache = tmp_path / "templates", tmp_path / "cache"
    templates.mkdir()
    cache.mkdir()
    (templates / "page.html").write_text(PAGE)
    return templates, cache


def test_a_later_run_renders_the_kept_code_without_compiling(folders):
    templates, cache = folders
    first, calls = counting(environment(templates, cache))
    html = first.get_template("page.html").render(items=["a", "<b>"])
    assert calls == ["page.html"]
    assert len(list(cache.iterdir())) == 1
    later = never_compiles(environment(templates, cache))  # a new process's environment
    assert later.get_template("page.html").render(items=["a", "<b>"]) == html
    assert html == "<li>a</li><li>&lt;b&gt;</li>"


def test_a_changed_template_is_compiled_again(folders):
    templates, cache = folders
    environment(templates, cache).get_template("page.html").render(items=[1])
    (templates / "page.html").write_text("{{ items | length }} items")
    env, calls = counting(environment(templates, cache))
    assert env.get_template("page.html").render(items=[1, 2]) == "2 items"
    assert calls == ["page.html"]


def test_code_of_another_jinja_version_is_not_used(folders, monkeypatch):
    templates, cache = folders
    environment(templates, cache).get_template("page.html").render(items=[1])
    monkeypatch.setattr(jinja2, "__version__", "0.0-other")
    env, calls = counting(environment(templates, cache))
    env.get_template("page.html").render(items=[1])
    assert calls == ["page.html"]
    assert len(list(cache.iterdir())) == 2  # each version its own entry


@pytest.mark.parametrize("damage", [b"", b"garbage", b"j2\x80\x02K\x05.truncated"])
def test_a_damaged_entry_is_compiled_around(folders, damage):
    templates, cache = folders
    environment(templates, cache).get_template("page.html").render(items=[1])
    (entry,) = cache.iterdir()
    entry.write_bytes(damage)
    env, calls = counting(environment(templates, cache))
    assert env.get_template("page.html").render(items=["x"]) == "<li>x</li>"
    assert calls == ["page.html"]


def test_a_folder_that_cannot_be_written_only_costs_the_compile(folders):
    templates, cache = folders
    blocked = cache / "a-file"
    blocked.write_text("not a folder")  # every write under it fails (ENOTDIR), even as root
    env, calls = counting(environment(templates, blocked))
    assert env.get_template("page.html").render(items=["x"]) == "<li>x</li>"
    assert calls == ["page.html"]


def test_no_cache_where_the_default_folder_is_not_safely_the_users(tmp_path, monkeypatch):
    # Jinja's default folder is $TMPDIR/_jinja2-cache-<uid>; something else in its place (here
    # a file) is refused, and the templates are then compiled every run.
    monkeypatch.setattr(tempfile, "gettempdir", lambda: str(tmp_path))
    (tmp_path / f"_jinja2-cache-{os.getuid()}").write_text("planted")
    assert compiled_template_cache() is None


def test_the_default_folder_is_private(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "gettempdir", lambda: str(tmp_path))
    cache = compiled_template_cache()
    assert cache is not None
    folder = tmp_path / f"_jinja2-cache-{os.getuid()}"
    assert folder.is_dir() and folder.stat().st_mode & 0o777 == 0o700


def test_the_reports_render_the_same_with_and_without_kept_code(tmp_path, monkeypatch):
    context = {"title": "a < b"}
    html_report._environment.cache_clear()
    monkeypatch.setattr(tempfile, "gettempdir", lambda: str(tmp_path))
    try:
        cold = html_report.render_page("base.html.j2", context)  # compiled and kept
        html_report._environment.cache_clear()
        warm_env = never_compiles(html_report._environment())
        assert warm_env.get_template("base.html.j2").render(**context) == cold
    finally:
        html_report._environment.cache_clear()
    assert list((tmp_path / f"_jinja2-cache-{os.getuid()}").iterdir())
