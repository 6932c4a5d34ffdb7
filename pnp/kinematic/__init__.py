"""The fast kinematic backend (``backend="kinematic"``): the PnP worlds in pure batched
torch, no physics engine (``backend``), one HL step of them (``step``) and the optional
robot-box pushes (``contact``)."""
