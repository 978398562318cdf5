-- Rendezvous filter consistency per frame (issue 23, point 6 c) and the error against range with the filter's
-- stated sigma (point 5's figure): over the approaches of one run ($run), at each frame.
-- m, m/s; nees: 6 dof, nees_pos: 3 dof; *_first: over the approaches with case_id < $first only (point 6 c states
-- its bound for 100 approaches); z2_*: the mean squared position error over the stated sigma per Hill axis (x
-- radial, y along-track, z cross-track; 1 where that sigma is right): which axis a NEES off its bounds comes from.
SELECT frame, avg(t_s) AS t_s, count(*) AS approaches, avg(nees) AS mean_nees, avg(nees_pos) AS mean_nees_pos,
       count(*) FILTER (WHERE case_id < $first) AS approaches_first,
       avg(nees) FILTER (WHERE case_id < $first) AS mean_nees_first,
       avg(range_m) AS range_mean_m, sqrt(avg(pos_err_m * pos_err_m)) AS pos_err_rms_m,
       sqrt(avg(sigma_pos_m * sigma_pos_m)) AS sigma_pos_rms_m, sqrt(avg(range_err_m * range_err_m)) AS range_err_rms_m,
       sqrt(avg(vel_err_m_s * vel_err_m_s)) AS vel_err_rms_m_s, avg(bearing_used::INT) AS availability,
       avg(((est_x - true_x) / sigma_x) ** 2) AS z2_radial, avg(((est_y - true_y) / sigma_y) ** 2) AS z2_along,
       avg(((est_z - true_z) / sigma_z) ** 2) AS z2_cross
FROM rendezvous_frames WHERE run = $run
GROUP BY frame ORDER BY frame;
