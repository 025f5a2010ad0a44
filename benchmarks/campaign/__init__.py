"""A measurement campaign that survives sessions (issue 68): a queue of cells (method x subject x seed x setting) that
a background runner trains and evaluates at the lowest CPU priority while other work goes on, committing each finished
cell's metrics to ``benchmarks/results/<result>.json`` (and its tables to ``<result>.md``) as it completes.

Commands (from the repository root; ``make campaign`` starts it)::

    python -m benchmarks.campaign start     # the runner in the background, in a session of its own; returns at once
    python -m benchmarks.campaign status    # finished, in progress, failed and left; the runner's pid and priority
    python -m benchmarks.campaign stop      # ends the cells in progress (at most those are lost) and the runner
    python -m benchmarks.campaign run       # the runner in the foreground (Ctrl-C stops it)
    python -m benchmarks.campaign table     # the tables from the finished cells, missing ones marked

Starting it is the first thing a session does while a campaign is open. The queue is
``benchmarks/campaign/queue.toml``; :mod:`.cells` reads it, :mod:`.priority` lowers the runner's priority (its own
nice, SCHED_IDLE, and its autogroup's nice), :mod:`.runner` runs the cells, :mod:`.results` keeps the result file and
:mod:`.tables` renders it.
"""
