-- What Table 5's "stars observed" counts, per successful case (averages over the successful cases, as Table 5).
-- "Stars generated" (star_cases.n_generated) counts the catalog stars whose centre lies inside the image;
-- "stars observed" (star_cases.n_observed) counts every blob the detector found, one row of star_detections each.
-- A blob is matched when a rendered star lies within 2 px of its centroid (star_detections.hip_true >= 0,
-- nav/truth_match.py); rendered stars include those centred up to the PSF's reach outside the frame, whose
-- light spills in.  So observed = matched + false, and matched blobs split into:
--   edge blobs   the centroid lies nearer the border than its star (true_dist_px > distance to the border):
--                every blob of a star centred outside the image is one (its centroid is inside, its star
--                beyond the border), so these are the stars observed but never generated;
--   split blobs  a second (third...) blob of a star that already has one;
-- and missed = generated stars with no blob = generated - distinct stars matched by a non-edge blob (never < 0).
-- Parameters: $run, $width, $height (the camera's pixels, from the run's spec), $max_case: only cases with a
-- smaller id (cases are independent draws, so the first ones are a random sample; bounds the scan of a huge run).
WITH s AS (
    SELECT case_id, n_generated, n_observed FROM star_cases
    WHERE run = $run AND status = 'success' AND case_id < $max_case
), d AS (
    SELECT case_id,
           count(*)                                                                   AS blobs,
           count(*) FILTER (WHERE hip_true >= 0)                                      AS matched,
           count(*) FILTER (WHERE hip_true < 0)                                       AS false_blobs,
           count(*) FILTER (WHERE hip_true >= 0 AND true_dist_px
                            > least(x_px, y_px, $width - x_px, $height - y_px))       AS edge_blobs,
           count(*) FILTER (WHERE hip_true >= 0)
             - count(DISTINCT hip_true) FILTER (WHERE hip_true >= 0)                  AS split_blobs,
           count(DISTINCT hip_true) FILTER (WHERE hip_true >= 0 AND NOT true_dist_px
                            > least(x_px, y_px, $width - x_px, $height - y_px))       AS stars_inside_found
    FROM star_detections WHERE run = $run AND case_id < $max_case AND case_id IN (SELECT case_id FROM s)
    GROUP BY case_id
)
SELECT count(*)                                                                       AS cases,
       avg(s.n_generated)                                                             AS generated,
       avg(s.n_observed)                                                              AS observed,
       avg(coalesce(d.blobs, 0))                                                      AS blobs,
       avg(coalesce(d.matched, 0))                                                    AS matched,
       avg(coalesce(d.edge_blobs, 0))                                                 AS edge,
       avg(coalesce(d.split_blobs, 0))                                                AS split,
       avg(coalesce(d.false_blobs, 0))                                                AS false_blobs,
       avg(greatest(s.n_generated - coalesce(d.stars_inside_found, 0), 0))            AS missed,
       count(*) FILTER (WHERE s.n_observed > s.n_generated)                          AS cases_observed_gt_generated
FROM s LEFT JOIN d USING (case_id);
