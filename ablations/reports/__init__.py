"""The reports wing: what turns run folders (and benchmark files, memory sweeps) into figures, seed statistics and
markdown reports. It reads JSON and draws with matplotlib; nothing here imports torch to read or compute.

Its modules import one way, each only those above it in this list:

    stats/         statistics over seeds (curves, bootstrap estimates, paired comparisons, probes, verdicts)
    paper_numbers  the D.Va paper's numbers, each with its citation
    style          run grouping and labels, arm styles, floors, the mean band, palette PNGs
    seed_figures   the seed statistics' figures (learning curves, paired differences, performance profiles)
    plot           the figures of run folders' metrics (``ablate-plot``)
    parts          what every report section builds with: run facts, markdown tables, relative links
    arms           each run's arm, each arm's iteration time alone
    seeds          the seed-statistics and probe sections
    report         ``ablate-report``
    paper          ``ablate-paper``'s report of its sweep folder (the command is ``ablations.paper``)
"""

from ablations.reports.arms import arm_label, arm_names, iteration_times
from ablations.reports.plot import FIGURES, PlotConfig, build_figures, make_plots, plot_runs
from ablations.reports.report import ReportConfig, build_report
from ablations.reports.seeds import probe_section, seed_section, seed_statistics
from ablations.reports.style import Floors, load_floors, png_bytes

__all__ = ["FIGURES", "Floors", "PlotConfig", "ReportConfig", "arm_label", "arm_names", "build_figures",
           "build_report", "iteration_times", "load_floors", "make_plots", "plot_runs", "png_bytes", "probe_section",
           "seed_section", "seed_statistics"]
