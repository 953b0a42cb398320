"""The one check of r, u, y against a model (core/logged_data.py): error paths name the signal."""

import numpy as np
import pytest

from mpm_monitor.core.errors import DataFileError
from mpm_monitor.core.logged_data import LoggedData, check_loop_data, check_signals
from mpm_monitor.core.model import PlantModel

MODEL = PlantModel(1.0, ["u1", "u2"], ["y1"], gain=[[1.0, 2.0]], time_constant=[[3.0, 4.0]], delay=[[0.0, 1.0]])


def _data(n=5, **kw):
    base = dict(t=np.arange(n, dtype=float), r=np.zeros((n, 1)), u=np.ones((n, 2)), y=np.zeros((n, 1)),
                inputs=("u1", "u2"), outputs=("y1",), sample_time=1.0, source="log.csv")
    base.update(kw)
    return LoggedData(**base)


def test_good_data_come_back_as_float_arrays():
    r, u, y = check_loop_data(MODEL, _data(u=np.ones((5, 2), dtype=int)))
    assert r.shape == (5, 1) and u.dtype == float and y.shape == (5, 1)
    one = check_signals([0.0], [1, 2], [3.0], 1, 2)
    assert [a.shape for a in one] == [(1,), (2,), (1,)]


@pytest.mark.parametrize("kw,match", [
    (dict(u=np.ones((5, 3))), r"log.csv: input: expected shape \(5, 2\), got \(5, 3\)"),
    (dict(y=np.zeros((4, 1))), r"log.csv: output: expected shape \(5, 1\), got \(4, 1\)"),
    (dict(r=np.array([[0.0], [np.nan], [0.0], [0.0], [0.0]])), r"log.csv: setpoint: values contain NaN or infinity"),
    (dict(inputs=("u2", "u1")), r"log.csv: channels \['u2', 'u1'\] / \['y1'\] do not match the model's inputs"),
])
def test_bad_data_name_the_source_and_the_signal(kw, match):
    with pytest.raises(DataFileError, match=match):
        check_loop_data(MODEL, _data(**kw))


def test_one_sample_of_the_wrong_length_or_not_finite():
    with pytest.raises(DataFileError, match=r"^input: expected shape \(2,\), got \(1,\)"):
        check_signals([0.0], [1.0], [0.0], 1, 2)
    with pytest.raises(DataFileError, match=r"^output: values contain NaN or infinity"):
        check_signals([0.0], [1.0, 2.0], [np.inf], 1, 2)
