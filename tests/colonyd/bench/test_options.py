"""The benchmarks' shared options: comma-separated names checked at parse time, `--alignment`."""

from __future__ import annotations

import argparse

import pytest

from colonyd.bench.options import alignment_option, names


def test_names_parse_to_a_list_and_an_unknown_one_is_refused_saying_what_was_expected(capsys):
    parser = argparse.ArgumentParser(prog="bench")
    parser.add_argument("--runs", type=names(("a", "b")), default="a")
    alignment_option(parser, "the fixes")
    args = parser.parse_args([])
    assert args.runs == ["a"] and args.alignment == "noise"  # the string default is parsed too
    assert parser.parse_args(["--runs", "b,a", "--alignment", "state"]).runs == ["b", "a"]
    with pytest.raises(SystemExit):
        parser.parse_args(["--runs", "a,c"])
    err = capsys.readouterr().err
    assert "argument --runs: expected names of ('a', 'b'), found 'a,c'" in err
