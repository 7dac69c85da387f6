"""The error budget of a reconstruction: a ladder of oracles whose steps say where the decibels go.

* :mod:`.oracles`: the oracle captures (model-exact, noise-free) of a capture;
* :mod:`.ladder`: the rungs of one case and their telescoping steps;
* :mod:`.runner`: every case of a suite, in this process or on Dask, resumable;
* :mod:`.budget_report`: the report table, the waterfall plots and the results page.
* :mod:`.findings`: the results page's generated findings (model fidelity, the issue's three cases).
"""
