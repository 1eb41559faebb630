"""Running comparisons: experiments (one selector, one seed), executors and the compare task.
"""
