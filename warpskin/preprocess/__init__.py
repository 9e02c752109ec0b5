"""Host-side preprocessing that turns a closed rig into the multi-layer simulation model
(Deul & Bender 2013, sections 3, 4.3, 4.4, 4.6): layers, masses, regions, fast-summation paths,
sub-volumes, joint constraints and automatic weights."""
