"""Test doubles, synthetic data and oracles shared by the test modules (imported as ``helpers.<module>``;
``tests/`` is on ``sys.path`` because ``tests/conftest.py`` lives there). The shared pytest fixtures are
in ``tests/conftest.py``."""
