"""psimap.sim: load exported scenes into MuJoCo and check them (penetration, settling, stability).

Installed as `psimap.sim` (never as a top-level `sim`).
"""
