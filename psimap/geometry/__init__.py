"""psimap/geometry"""
