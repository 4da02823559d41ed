"""The demo's closing words (issue 28 item 2): a test that ends early still says what had been
found before the stop (t_life, the warning), and the words say where the warning's lead came from
(the result's warn_reasons: prior, trend, headroom)."""
from gateway.cli.demo import AFTER_LIFE, _lead_words, _plain_words

TS = 0.02


def _result(**kw):
    m = {"status": "failure", "t_life": 211.3, "warn_slot": 8499, "warn_reasons": ["prior"],
         "mu_ss": 0.2, "mu_th": 0.25}
    m.update(kw)
    return m


def test_an_early_end_after_the_end_of_life_says_what_was_found():
    words = _plain_words(_result(), {"k_detect": 11064}, 200.4, 10.0, TS, True, False,
                         "protection stop")
    assert words.startswith("the test ended early (protection stop); before the stop; "
                            "the hook reached its end of life 211.3 s after the start"), words
    assert "detected 10.0 s later (the 10 s persistence)" in words
    assert "warned 41.3 s before the end of life (reasons: prior)" in words
    assert words.endswith("offline analysis of the recorded log agrees")


def test_an_early_end_before_the_end_of_life_still_tells_the_warning():
    words = _plain_words(_result(t_life=None, status="aborted"), {}, None, 10.0, TS, True, False,
                         "protection stop")
    assert words.startswith("the test ended early (protection stop); before the stop; no end of "
                            "life was found (status aborted)"), words
    assert "warned at 170.0 s (reasons: prior)" in words


def test_a_completed_life_reads_as_before():
    words = _plain_words(_result(), {"k_detect": 11064}, 200.4, 10.0, TS, True, True, "completed")
    assert words.startswith("the hook reached its end of life 211.3 s after the start; detected")
    assert "ended early" not in words


def test_the_lead_is_explained_from_warn_reasons():
    assert _lead_words(_result(warn_reasons=["headroom", "prior"])) == (
        "its lead came from the wear headroom (μ close to μ_th for n_warn windows) and the life "
        "prior (what earlier hooks of this grade at this T_set lasted)")
    assert "the trend of μ" in _lead_words(_result(warn_reasons=["trend"]))
    assert _lead_words(_result(warn_slot=None, warn_reasons=None)) == ""


def test_the_after_life_line_is_the_contract():
    # another helper's CI script waits for exactly this line, then sends SIGINT
    assert AFTER_LIFE == ("hookwatch demo: the life is over; the console and the broker stay up "
                          "until Ctrl-C")
