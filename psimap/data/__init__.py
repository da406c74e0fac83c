"""psimap/data"""
