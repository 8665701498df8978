"""The colour of each model, by its place in the job's list of models: the same in the
figures of ``abcns plot`` (service/report/plots.py) and on the live page
(service/http/page.py)."""

#: matplotlib's "tab10" colours (tab:blue, tab:orange, ...), as hex codes for the page
MODEL_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
                 "#bcbd22", "#17becf")


def model_colour(i: int) -> str:
    """The colour of the job's model ``i`` (0-based)."""
    return MODEL_COLOURS[i % len(MODEL_COLOURS)]
