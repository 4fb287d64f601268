"""The suite's annotation checks (conftest.py `_check_annotations`) are on in every module of
jaxtable: array shapes and named dimensions where jaxtyping annotations are, plain types
everywhere else."""

import importlib
import sys

import numpy as np
import pytest
from conftest import annotation_checks


def test_every_module_is_loaded_by_one_of_the_two_checkers():
    import jaxtable  # noqa: F401

    by_jaxtyping, by_beartype = annotation_checks()
    assert by_jaxtyping and by_beartype
    for name in by_jaxtyping + by_beartype:
        if name == "jaxtable" or name.endswith("__main__"):  # no function; a script
            continue
        module = sys.modules.get(name) or importlib.import_module(name)
        loader = type(module.__spec__.loader).__name__
        expected = "_JaxtypingLoader" if name in by_jaxtyping else "BeartypeSourceFileLoader"
        assert loader == expected, (name, loader)


def test_a_named_dimension_that_disagrees_across_arguments_is_refused():
    """`solve_small(A: "n n", B: "n k")`: a (3, 3) A with a (4, 1) B is refused by the
    dimension memo of `@jaxtyped`, which a per-argument check would pass."""
    from jaxtyping import TypeCheckError

    from jaxtable._linalg import solve_small

    np.testing.assert_allclose(solve_small(2.0 * np.eye(3), np.ones((3, 1))), 0.5 * np.ones((3, 1)))
    with pytest.raises(TypeCheckError, match="B"):
        solve_small(np.eye(3), np.ones((4, 1)))


def test_a_plain_annotation_outside_the_array_modules_is_checked():
    """...and raises the same TypeError (jaxtyping's TypeCheckError) as an array module's."""
    from jaxtyping import TypeCheckError

    from jaxtable._calibration.fit import Layout
    from jaxtable._params import leaf

    assert leaf("thermal.alpha[all]") == "thermal.alpha"
    with pytest.raises(TypeCheckError, match="name"):
        leaf(3)
    with pytest.raises(TypeCheckError, match="n_sessions"):
        Layout((), (), (), "two", ())
