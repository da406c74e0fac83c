"""psimap/panoptic"""
