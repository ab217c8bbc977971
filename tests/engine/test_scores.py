"""The run's score summary: the earliest of tied best evaluations, and a final score over the last three."""
from drop_engine.scores import ScoreSummary, summarize


def test_summary_keeps_the_earliest_best_and_averages_the_last_three():
    assert summarize([(1, 2.0), (2, 8.0), (3, 8.0), (4, 5.0), (5, 2.0)]) == ScoreSummary(2.0, 8.0, 2, 5.0)
    assert summarize([(10, 4.0), (20, 6.0)]) == ScoreSummary(6.0, 6.0, 20, 5.0)
    assert summarize([]) == ScoreSummary(None, None, None, None)
