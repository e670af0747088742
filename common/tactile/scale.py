"""The tactile sensor's force scale in plain numbers: its floor and its ceiling.

Part of the tactile contract (``common.tactile.contract`` re-exports both), kept apart
from its NumPy so that what needs only the scale imports no NumPy: the
operator's contact mapping, read by ``deepxpalm palm lift``, whose start-up
is the time a dead operator node's linkages stay on the palm.
"""

#: the sensor's ceiling: a taxel above this reads this, and no stimulus exceeds it
SATURATION_N = 9.0
#: the sensor's floor: a taxel below this reads 0, and a frame reaching it holds a grasp
CONTACT_FLOOR_N = 1.0
