"""Maps from many sessions: a run's result as a one-session map, sessions placed and merged.

``session_map_from_result`` makes a :class:`~submapslam.session_map.SessionMap` of one run;
``merge_sessions`` places further sessions against it (:mod:`submapslam.topology.session_placement`)
and optimises the merged graph (:mod:`submapslam.backend`), one map in one frame;
``SessionMerger`` does the same one session at a time (``batch`` merges each log as it is done);
``drop_sessions`` takes sessions out of a map, the others left where they are.
"""

from .edit import drop_sessions
from .merge import SessionMerger, merge_sessions, session_map_from_result, session_names

__all__ = ["SessionMerger", "drop_sessions", "merge_sessions", "session_map_from_result", "session_names"]
