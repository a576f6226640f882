"""provenance: the commit and the modified files of the checkout, or a clear 'unknown'."""

import re

from ne_jax import provenance


def test_commit_is_a_hash_or_unknown():
    full, short = provenance.commit(), provenance.commit(short=True)
    if full == "unknown":  # not a git checkout (e.g. an installed copy)
        assert short == "unknown"
        return
    assert re.fullmatch(r"[0-9a-f]{40}", full) and full.startswith(short) and 4 <= len(short) < 40


def test_modified_lists_paths_relative_to_the_checkout():
    for path in provenance.modified():
        assert path and not path.startswith((" ", "/"))
    assert provenance.modified("no/such/path") == []
