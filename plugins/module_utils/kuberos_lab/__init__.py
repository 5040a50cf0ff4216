"""The local lab: what the project starts on this machine to stand in for a site's machines and services.

Only the lab uses it (the local_cluster role, the tests, the benchmarks); a real site has these parts of its own.
`registry`: the CNCF distribution registry with TLS and htpasswd authentication, and a client of the registry
API that pushes image archives by digest and checks images.
"""
