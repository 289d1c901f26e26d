"""bench/cases/real.py: what the capture cleaning repaired, counted from its report."""
from __future__ import annotations


def test_cleaning_counts_runs_samples_and_frames():
    from bench.cases.real import cleaning_counts

    rep = {"removed_samples": 7, "unswapped": {"LWRA": 140, "RWRA": 140},
           "runs": [{"marker": "LWRA", "reason": "swap", "first_sample": 10, "last_sample": 149},
                    {"marker": "RWRA", "reason": "swap", "first_sample": 10, "last_sample": 149},
                    {"marker": "LKNE", "reason": "spike", "first_sample": 300, "last_sample": 300},
                    {"marker": "C7", "reason": "ghost", "first_sample": 148, "last_sample": 153}]}
    got = cleaning_counts(rep)
    assert got == {"cleaned_runs": 4.0, "cleaned_samples": 7.0,
                   "cleaned_frames": 140.0 + 4 + 1, "unswapped_samples": 280.0}
    assert cleaning_counts(None) == {"cleaned_runs": 0.0, "cleaned_samples": 0.0,
                                     "cleaned_frames": 0.0, "unswapped_samples": 0.0}
