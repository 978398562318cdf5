-- Star tracking campaign (issue 22, point 5): availability, first fix, re-acquisition, false locks, rate error and
-- its consistency with the stated sigmas (the attitude filter's rate against the true rate at the frame too), degraded frames (an attitude the tracker withheld: its stated sigma above
-- tracking.max_sigma_rad; $limit: the error limit in arcsec), identities of tracking against lost-in-space on the same frames.
-- Full scan of star_frames and star_sequences of one run ($run); rates in deg/s, errors in arcsec.
WITH f AS (SELECT * FROM star_frames WHERE run = $run),
s AS (SELECT * FROM star_sequences WHERE run = $run),
last AS (SELECT case_id, max(frame) AS last_frame FROM f GROUP BY case_id),
blind AS (    -- frames from each blinded frame to the next valid attitude of its sequence (null: none followed), and
              -- whether it can be judged: re-acquired, or at least 2 frames left after it (else the sequence ended)
    SELECT b.case_id, b.frame, min(v.frame) - b.frame AS reacq,
           (min(v.frame) IS NOT NULL OR any_value(l.last_frame) - b.frame >= 2) AS judged
    FROM f b JOIN last l ON l.case_id = b.case_id LEFT JOIN f v ON v.case_id = b.case_id AND v.frame > b.frame AND v.valid
    WHERE b.event = 'blinded' GROUP BY b.case_id, b.frame
),
re AS (SELECT unnest(reacquisition_frames) AS n FROM s),
rate AS (
    SELECT (rate_att_x_deg_s - true_rate_mean_x_deg_s) AS ex, (rate_att_y_deg_s - true_rate_mean_y_deg_s) AS ey,
           (rate_att_z_deg_s - true_rate_mean_z_deg_s) AS ez, rate_att_sigma_x_deg_s AS sx,
           rate_att_sigma_y_deg_s AS sy, rate_att_sigma_z_deg_s AS sz
    FROM f WHERE rate_att_x_deg_s IS NOT NULL
),
frate AS (    -- the attitude filter's rate against the true rate at the frame
    SELECT (rate_filter_x_deg_s - true_rate_x_deg_s) AS ex, (rate_filter_y_deg_s - true_rate_y_deg_s) AS ey,
           (rate_filter_z_deg_s - true_rate_z_deg_s) AS ez, rate_filter_sigma_x_deg_s AS sx,
           rate_filter_sigma_y_deg_s AS sy, rate_filter_sigma_z_deg_s AS sz
    FROM f WHERE rate_filter_x_deg_s IS NOT NULL
),
srate AS (
    SELECT (rate_star_x_deg_s - true_rate_mean_x_deg_s) AS ex, (rate_star_y_deg_s - true_rate_mean_y_deg_s) AS ey,
           (rate_star_z_deg_s - true_rate_mean_z_deg_s) AS ez, rate_star_sigma_x_deg_s AS sx,
           rate_star_sigma_y_deg_s AS sy, rate_star_sigma_z_deg_s AS sz
    FROM f WHERE rate_star_x_deg_s IS NOT NULL
)
SELECT
    (SELECT count(*) FROM s)                                                    AS sequences,
    (SELECT count(*) FROM f)                                                    AS frames,
    (SELECT count(*) FILTER (WHERE event = 'normal') FROM f)                    AS frames_normal,
    (SELECT avg(within_limit::INT) FROM f)                                      AS availability,
    (SELECT avg(within_limit::INT) FILTER (WHERE event = 'normal') FROM f)      AS availability_normal_frames,
    (SELECT count(*) FILTER (WHERE event = 'crossing') FROM f)                  AS frames_crossing,
    (SELECT avg(within_limit::INT) FILTER (WHERE event = 'crossing') FROM f)    AS availability_crossing_frames,
    (SELECT count(*) FILTER (WHERE event = 'crossing' AND false_lock) FROM f)   AS false_locks_crossing_frames,
    (SELECT avg(valid::INT) FROM f)                                             AS valid_share,
    (SELECT avg((mode = 'tracking')::INT) FROM f)                               AS tracking_share,
    (SELECT sum(false_lock::INT) FROM f)                                        AS false_locks,
    (SELECT count(*) FILTER (WHERE two_star) FROM f)                            AS two_star_frames,
    (SELECT count(*) FILTER (WHERE degraded) FROM f)                            AS degraded_frames,
    (SELECT count(*) FILTER (WHERE degraded AND event = 'normal') FROM f)       AS degraded_normal_frames,
    (SELECT count(*) FILTER (WHERE degraded AND degraded_err_max_arcsec > $limit) FROM f)
                                                                                AS degraded_beyond_limit,
    (SELECT count(*) FILTER (WHERE event = 'normal' AND NOT valid AND NOT coalesce(degraded, false)) FROM f)
                                                                                AS normal_frames_without_answer,
    (SELECT avg(time_to_first_fix_s) FROM s)                                    AS mean_time_to_first_fix_s,
    (SELECT max(time_to_first_fix_s) FROM s)                                    AS max_time_to_first_fix_s,
    (SELECT count(*) FILTER (WHERE first_fix_frame IS NULL) FROM s)             AS sequences_never_fixed,
    (SELECT count(*) FROM re)                                                   AS reacquisitions,
    (SELECT avg(n) FROM re)                                                     AS mean_reacquisition_frames,
    (SELECT max(n) FROM re)                                                     AS max_reacquisition_frames,
    (SELECT sum(unrecovered_losses) FROM s)                                     AS unrecovered_losses,
    (SELECT count(*) FROM blind)                                                AS blinded_frames,
    (SELECT count(*) FILTER (WHERE judged) FROM blind)                          AS blinded_frames_judged,
    (SELECT avg(coalesce(reacq <= 2, false)::INT) FILTER (WHERE judged) FROM blind)
                                                                                AS blinded_reacquired_within_2,
    (SELECT max(reacq) FROM blind)                                              AS blinded_max_reacquisition_frames,
    (SELECT count(*) FROM rate)                                                 AS rate_frames,
    (SELECT sqrt(avg(ex * ex + ey * ey + ez * ez)) FROM rate)                   AS rate_att_err_rms_deg_s,
    (SELECT avg(((abs(ex) <= 3 * sx)::INT + (abs(ey) <= 3 * sy)::INT + (abs(ez) <= 3 * sz)::INT) / 3.0) FROM rate)
                                                                                AS rate_att_within_3sigma,
    (SELECT sqrt(avg(ex * ex + ey * ey + ez * ez)) FROM srate)                  AS rate_star_err_rms_deg_s,
    (SELECT avg(((abs(ex) <= 3 * sx)::INT + (abs(ey) <= 3 * sy)::INT + (abs(ez) <= 3 * sz)::INT) / 3.0) FROM srate)
                                                                                AS rate_star_within_3sigma,
    (SELECT count(*) FROM frate)                                                AS rate_filter_frames,
    (SELECT sqrt(avg(ex * ex + ey * ey + ez * ez)) FROM frate)                  AS rate_filter_err_rms_deg_s,
    (SELECT avg(((abs(ex) <= 3 * sx)::INT + (abs(ey) <= 3 * sy)::INT + (abs(ez) <= 3 * sz)::INT) / 3.0) FROM frate)
                                                                                AS rate_filter_within_3sigma,
    (SELECT count(*) FILTER (WHERE valid AND frame_sigma_max_arcsec > sigma_max_arcsec * 1.0001
                             AND frame_sigma_max_arcsec > (SELECT max(sigma_max_arcsec) FROM f WHERE valid)) FROM f)
                                                                                AS valid_by_the_filter_only,
    (SELECT sum(n_id_agree) FROM f)                                             AS ids_equal_to_lost_in_space,
    (SELECT sum(n_id_disagree) FROM f)                                          AS ids_different_from_lost_in_space;
