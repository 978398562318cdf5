-- Nightly metrics of one star SIL run ($run), one row per case (jobs/nightly/compare.py: METRICS["star"]).
-- Rates are booleans, error distributions doubles; NULL = not applicable to this case.
--   success, confident_wrong     status of the reference's method (every axis within 100 arcsec; failed with T > 0)
--   identification               every accepted identity right and at least two of them (id_correct)
--   *_robust                     the same for dualsight's robust method (NULL when the run has none)
--   err_{x,y,z}_arcsec           |Eqs. 4-7 error| per camera axis, over the successes
--   centroid_err_px              mean distance of the case's matched detections to their true star positions
WITH det AS (
    SELECT case_id, avg(true_dist_px) AS centroid_err_px
    FROM star_detections
    WHERE run = $run AND hip_true >= 0 AND NOT isnan(true_dist_px)
    GROUP BY case_id
)
SELECT c.case_id,
       c.status = 'success'                                                    AS success,
       c.status = 'confident_wrong'                                            AS confident_wrong,
       c.id_correct                                                            AS identification,
       c.status_robust = 'success'                                             AS success_robust,
       c.status_robust = 'confident_wrong'                                     AS confident_wrong_robust,
       CASE WHEN c.status = 'success' THEN abs(c.err_x_rad) * arcsec_per_rad() END AS err_x_arcsec,
       CASE WHEN c.status = 'success' THEN abs(c.err_y_rad) * arcsec_per_rad() END AS err_y_arcsec,
       CASE WHEN c.status = 'success' THEN abs(c.err_z_rad) * arcsec_per_rad() END AS err_z_arcsec,
       det.centroid_err_px
FROM star_cases c LEFT JOIN det USING (case_id)
WHERE c.run = $run
ORDER BY c.case_id;
