"""What an evaluation writes: an episode record's columns and the files of its folder.

Its own module so that running the episodes (:mod:`agents.learning.evaluation.run`) and writing
them (:mod:`agents.learning.evaluation.report`) both read it and neither imports the other's
internals back.
"""

#: Where a field's name starts with this, it is a wall-clock timing (never deterministic).
TIMING_PREFIX = "timing_"

#: The columns of ``episodes.csv``, in order (empty cells where a task has no such figure).
CSV_COLUMNS = (
    "episode",
    "seed",
    "return",
    "success",
    "length",
    "terminated",
    "truncated",
    "end",
    "tissue_status",
    "contact_force_mean_n",
    "contact_force_peak_n",
    "normal_force_mean_n",
    "centring_error_m",
    "lesion_lateral_end_m",
    "lesion_depth_end_m",
    "target_depth_m",
    "remaining_end_m",
    "good_share_end",
    "timing_step_ms_mean",
    "timing_step_ms_max",
    "timing_policy_ms_mean",
)

#: Every file an evaluation may write in its folder (the lesion plot only where the
#: observation has a lesion, the path plot only for ForceScan).
OUTPUT_FILES = (
    "episodes.json",
    "episodes.csv",
    "summary.json",
    "summary.md",
    "success_rate.png",
    "contact_force.png",
    "lesion_path.png",
    "scan_progress.png",
)
