"""The capture-processing service: HTTP API (FastAPI), Celery workers, job store, storage.

``service`` imports :mod:`pmvir`; :mod:`pmvir` never imports ``service``.

* :mod:`service.settings`  ``PMVIR_*`` environment configuration
* :mod:`service.app`       ``create_app()``: the /v1 API (routes in ``routes_jobs``, ``routes_files``)
* :mod:`service.store`     job state in Redis (the service's own keys)
* :mod:`service.storage`   job folders on disk, the capture layout, atomic publishing
* :mod:`service.uploads`, :mod:`service.zipped`   streamed, bounded, resumable uploads; zipped captures
* :mod:`service.queue`, :mod:`service.celery_app`, :mod:`service.runner`, :mod:`service.lease_keeper`   Celery and the job runs
* :mod:`service.openapi`   the committed OpenAPI document
* :mod:`service.testing`   the real stack as local processes, for tests and benchmarks
"""
