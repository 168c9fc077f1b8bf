"""`taichi-gs view`: a run folder in the browser.

``run_scene`` reads what a run folder holds per stage (plain data, no viser); ``app`` shows it with
viser (the optional extra ``taichi-gs[viewer]``), imported only when the viewer starts.
"""
