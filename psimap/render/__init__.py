"""psimap/render"""
