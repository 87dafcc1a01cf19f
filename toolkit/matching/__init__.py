"""Graph matching: conjugate graph, data costs, the MRF and its solvers (Ling & Qin 2022, §3.3.1, Eq. 1–4)."""
