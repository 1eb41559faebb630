"""Reporting: result tables, IOH traces and figures.
"""
