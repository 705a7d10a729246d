//! Plant agent: bridges a plant (the simulated AERO or a real rig's driver) to the controller.
