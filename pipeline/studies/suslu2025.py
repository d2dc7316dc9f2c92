"""Süslü, Kuran & Söken (2025), "Design of a visual pose estimation algorithm for Moon landing":
the published numbers a run is compared against (Table 1, the windows of Figs. 7-8 and the
crater-count statements of Fig. 4).

The report and the sweep take this `STUDY` and read nothing paper-specific from anywhere else.
"""

from __future__ import annotations

from pipeline.studies import FigureWindow, RefLine, Study

# The paper's Table 1: RMSE over 1,800-2,400 s per crater cap (None: no limit), body-axis names;
# the paper scored attitude most likely about MCI axes (see README), the sweep compares both.
TABLE1: dict[int | None, dict[str, float]] = {
    10: {"x_m": 4.923, "y_m": 9.7451, "z_m": 9.3482, "phi_deg": 0.0039, "theta_deg": 0.0066,
         "psi_deg": 0.0066},
    20: {"x_m": 3.2534, "y_m": 6.2719, "z_m": 6.1251, "phi_deg": 0.0026, "theta_deg": 0.0042,
         "psi_deg": 0.0042},
    50: {"x_m": 1.9981, "y_m": 3.877, "z_m": 3.6869, "phi_deg": 0.0016, "theta_deg": 0.0025,
         "psi_deg": 0.0025},
    100: {"x_m": 1.4021, "y_m": 2.6237, "z_m": 2.6092, "phi_deg": 0.0011, "theta_deg": 0.0018,
          "psi_deg": 0.0018},
    200: {"x_m": 0.9739, "y_m": 1.8795, "z_m": 1.8001, "phi_deg": 0.00079, "theta_deg": 0.0012,
          "psi_deg": 0.0012},
    None: {"x_m": 0.6111, "y_m": 1.1499, "z_m": 1.1181, "phi_deg": 0.00049,
           "theta_deg": 0.00076, "psi_deg": 0.00076},
}

TABLE1_WINDOW_S = (1800.0, 2400.0)

# Figs. 7 and 8: position errors per cap before 1,500 s and in the Table 1 window.
CAP_FIGURE_WINDOWS = (FigureWindow("7", 0.0, 1500.0), FigureWindow("8", 1800.0, 2400.0))

# Fig. 4: fewer than 150 visible craters before 1,500 s; about 900 between 1,500 and 2,850 s.
COUNT_REFS = (RefLine(150.0, "paper: < 150 before 1,500 s", None, 1500.0),
              RefLine(900.0, "paper: peak ~ 900 (1,500-2,850 s)", 1500.0, 2850.0))

STUDY = Study(
    key="suslu2025",
    citation="Süslü, Kuran & Söken (2025), Design of a visual pose estimation algorithm for Moon "
             "landing",
    table1=TABLE1,
    table_window=TABLE1_WINDOW_S,
    cap_figure_windows=CAP_FIGURE_WINDOWS,
    count_refs=COUNT_REFS,
)

