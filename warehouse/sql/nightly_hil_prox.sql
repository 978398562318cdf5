-- Nightly metrics of one proximity HIL run ($run), one row per image x threshold (METRICS["hil_prox"]).
--   found                        a target blob was found;  within: true range in [range_min, range_max]
--   range_rel_err                |estimate - true| / true;  range_bias: (estimate - true) / true (with truth)
SELECT case_id, threshold,
       error IS NULL AND coalesce(found, false)                                AS found,
       CASE WHEN truth_range_m IS NOT NULL AND error IS NULL THEN within_min_max END AS within,
       CASE WHEN found AND truth_range_m IS NOT NULL THEN rel_error END        AS range_rel_err,
       CASE WHEN found AND truth_range_m IS NOT NULL THEN range_error_m / truth_range_m END AS range_bias
FROM hil_prox
WHERE run = $run
ORDER BY case_id, threshold;
