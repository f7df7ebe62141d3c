"""Helpers of the tests (and of the benchmarks), not tests themselves: phantom brains and stacks
(:mod:`~tests.support.phantoms`), hostile and valid uploads (:mod:`~tests.support.corpus`), a real
server and workers in subprocesses (:mod:`~tests.support.live_server`) and a real ``redis-server``
(:mod:`~tests.support.redis_server`)."""
