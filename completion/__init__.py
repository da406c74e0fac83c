"""psimap.completion: collision-aware completion of partially observed objects.

Installed as `psimap.completion`.
"""
