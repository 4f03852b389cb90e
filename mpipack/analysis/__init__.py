"""Analysis of scenes and results: the stability check before a run (``check``) and
post-processing of gathered configurations (``post``)."""
