"""psimap/metrics"""
