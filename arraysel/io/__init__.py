"""Files: atomic writers, the on-disk cache and mask-file parsing.
"""
