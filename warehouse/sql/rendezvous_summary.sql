-- Rendezvous campaign (issue 23, points 5-6): availability, bearing error and its stated sigma, the close-range
-- filtered range error against the single-frame blobber error and the velocity error from frame $after on (6 d),
-- the far-range position error as % of range one orbit after the first manoeuvre (6 e); the target found without
-- the truth (point 3): the share of frames with a detection of the true target where the filter picked it, the
-- picks that were not the target, the frames gated out.
-- Full scan of rendezvous_frames and rendezvous_cases of one run ($run); m, m/s, arcsec.
WITH f AS (SELECT * FROM rendezvous_frames WHERE run = $run),
c AS (SELECT * FROM rendezvous_cases WHERE run = $run),
b AS (SELECT * FROM f WHERE bearing_used),
late AS (SELECT * FROM f WHERE frame >= $after),
lr AS (SELECT * FROM late WHERE range_used),
o AS (SELECT * FROM f WHERE orbit_after_burn)
SELECT
    (SELECT count(*) FROM c)                                                     AS approaches,
    (SELECT count(*) FROM f)                                                     AS frames,
    (SELECT max(frame) + 1 FROM f)                                               AS frames_per_approach,
    (SELECT any_value(camera) FROM c)                                            AS camera,
    (SELECT avg(bearing_used::INT) FROM f)                                       AS availability,
    (SELECT avg(target_in_field::INT) FROM f)                                    AS in_field_share,
    (SELECT avg((attitude <> 'none')::INT) FROM f)                               AS attitude_share,
    (SELECT avg(range_used::INT) FROM f)                                         AS range_share,
    (SELECT count(*) FROM b)                                                     AS bearings,
    (SELECT avg(target_detected::INT) FROM f)                                    AS target_detected_share,
    (SELECT avg((bearing_used AND target_found_true)::INT) FROM f WHERE target_detected)
                                                                                 AS target_found_rate,
    (SELECT count(*) FROM b WHERE NOT target_found_true)                         AS target_false_picks,
    (SELECT count(*) FROM f WHERE target_found_by = 'gated_out')                 AS target_gated_out,
    (SELECT sqrt(avg(bearing_err_arcsec * bearing_err_arcsec)) FROM b)           AS bearing_err_rms_arcsec,
    (SELECT quantile_cont(bearing_err_arcsec, 0.5) FROM b)                       AS bearing_err_p50_arcsec,
    (SELECT quantile_cont(bearing_err_arcsec, 0.95) FROM b)                      AS bearing_err_p95_arcsec,
    (SELECT sqrt(avg(bearing_raw_err_arcsec * bearing_raw_err_arcsec)) FROM b)   AS bearing_raw_err_rms_arcsec,
    (SELECT sqrt(avg(bearing_sigma_arcsec * bearing_sigma_arcsec)) FROM b)       AS bearing_sigma_rms_arcsec,
    (SELECT avg((bearing_err_arcsec <= 3 * sqrt(2) * bearing_sigma_arcsec)::INT) FROM b)
                                                                                 AS bearing_within_3sigma,
    (SELECT count(*) FROM lr)                                                    AS late_range_frames,
    (SELECT sqrt(avg(range_err_m * range_err_m)) FROM lr)                        AS filtered_range_err_rms_m,
    (SELECT sqrt(avg((range_meas_m - range_m) * (range_meas_m - range_m))) FROM lr)
                                                                                 AS blobber_range_err_rms_m,
    (SELECT sqrt(avg(range_err_m * range_err_m / (range_m * range_m))) FROM lr)  AS filtered_range_err_rms_rel,
    (SELECT sqrt(avg((range_meas_m - range_m) * (range_meas_m - range_m) / (range_m * range_m))) FROM lr)
                                                                                 AS blobber_range_err_rms_rel,
    (SELECT count(*) FROM late)                                                  AS late_frames,
    (SELECT sqrt(avg(vel_err_m_s * vel_err_m_s)) FROM late)                      AS late_vel_err_rms_m_s,
    (SELECT max(vel_err_m_s) FROM late)                                          AS late_vel_err_max_m_s,
    (SELECT quantile_cont(vel_err_m_s, 0.95) FROM late)                          AS late_vel_err_p95_m_s,
    (SELECT count(*) FROM o)                                                     AS orbit_frames,
    (SELECT avg(range_m) FROM o)                                                 AS orbit_range_mean_m,
    (SELECT sqrt(avg(pos_err_m * pos_err_m / (range_m * range_m))) * 100 FROM o) AS orbit_pos_err_rms_pct,
    (SELECT quantile_cont(pos_err_m / range_m, 0.95) * 100 FROM o)               AS orbit_pos_err_p95_pct,
    (SELECT avg(sigma_pos_m / range_m) * 100 FROM o)                             AS orbit_sigma_mean_pct,
    (SELECT avg(nees) FROM o)                                                    AS orbit_mean_nees,
    (SELECT sqrt(avg(final_pos_err_m * final_pos_err_m)) FROM c)                 AS final_pos_err_rms_m,
    (SELECT sqrt(avg(final_vel_err_m_s * final_vel_err_m_s)) FROM c)             AS final_vel_err_rms_m_s,
    (SELECT avg(final_range_m) FROM c)                                           AS final_range_mean_m,
    (SELECT avg(t_total_ns) / 1e6 FROM c)                                        AS ms_per_approach,
    (SELECT avg(t_render_ns) / 1e6 FROM f)                                       AS render_ms_per_frame;
