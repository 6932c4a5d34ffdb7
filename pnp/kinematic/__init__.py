"""The fast kinematic backend (``backend="kinematic"``): the PnP worlds in pure batched
torch, no physics engine (``backend``), and one HL step of them (``step``)."""
