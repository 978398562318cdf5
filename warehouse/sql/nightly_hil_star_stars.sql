-- Nightly metrics of one star HIL run ($run), one row per identified star (METRICS["hil_star"]):
--   residual_arcsec              observed centroid vs the catalog star through the solved attitude
SELECT case_id, det_index, residual_rad * arcsec_per_rad() AS residual_arcsec
FROM hil_star_stars
WHERE run = $run
ORDER BY case_id, det_index;
