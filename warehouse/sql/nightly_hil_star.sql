-- Nightly metrics of one star HIL run ($run), one row per image (jobs/nightly/compare.py: METRICS["hil_star"]).
--   identified                   lost-in-space identification gave an attitude
--   success                      every axis within the status limit of the image's truth (NULL without truth)
--   boresight_err_arcsec         solved boresight vs the truth's, over identified images with truth
--   attitude_err_arcsec          rotation angle between solved and true attitude, same images
SELECT case_id,
       coalesce(identified, false)                                             AS identified,
       CASE WHEN truth_source <> 'none' THEN status = 'success' END            AS success,
       CASE WHEN identified THEN boresight_error_rad * arcsec_per_rad() END  AS boresight_err_arcsec,
       CASE WHEN identified THEN attitude_error_rad * arcsec_per_rad() END   AS attitude_err_arcsec
FROM hil_star
WHERE run = $run
ORDER BY case_id;
