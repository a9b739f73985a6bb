"""The bad-input corpus: :mod:`.make_corpus` generates it, ``test/test_bad_inputs.py`` runs it."""
