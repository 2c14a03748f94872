"""drivectl.profiles: reference trajectories r, r', r'', r''' for one axis.

Built-in kinds: :class:`PointToPoint` (jerk-limited, via ruckig), :class:`Circle` (paper 004 eq 25),
:class:`Dwell`, :class:`Sequence` (and :func:`back_and_forth`); TOML files and the built-in library via
:func:`load_profile` / :func:`list_profiles`; :func:`check_limits` refuses a profile before anything moves.
"""

from drivectl.profiles.base import Profile, ProfileError, Reference, check_limits
from drivectl.profiles.circle import Circle
from drivectl.profiles.dwell import Dwell
from drivectl.profiles.library import list_profiles, load_profile
from drivectl.profiles.ptp import PointToPoint
from drivectl.profiles.sequence import Sequence, back_and_forth

__all__ = [
    "Circle",
    "Dwell",
    "PointToPoint",
    "Profile",
    "ProfileError",
    "Reference",
    "Sequence",
    "back_and_forth",
    "check_limits",
    "list_profiles",
    "load_profile",
]
