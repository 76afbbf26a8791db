"""The mutation list (scripts/mutations.yaml) stays applicable as the code moves: each
entry is complete, its snippet occurs exactly once in its file, and the tests it names
exist. (A stale entry stops ``scripts/mutate.py``; this finds it in the suite, before a
mutation run.)"""

from __future__ import annotations

import pytest

from mysim_jax.bench.mutation import MUTATIONS, ROOT, check_snippets, load_mutations


def test_every_mutation_applies_once_and_names_existing_tests():
    mutations = load_mutations(MUTATIONS)
    assert len(mutations) > 50
    check_snippets(ROOT, mutations)          # exits naming the stale entries
    missing = [f"{m.id}: {t}" for m in mutations for t in m.selection
               if t.startswith("tests/") and not (ROOT / t.split("::")[0]).is_file()]
    assert not missing, "mutations naming tests that do not exist: " + ", ".join(missing)


def test_a_stale_snippet_is_named(tmp_path):
    mutations = load_mutations(MUTATIONS)[:1]
    (tmp_path / mutations[0].file).parent.mkdir(parents=True)
    (tmp_path / mutations[0].file).write_text("nothing of the original here\n")
    with pytest.raises(SystemExit, match=mutations[0].id):
        check_snippets(tmp_path, mutations)
