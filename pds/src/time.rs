//! PDS3 time values (Planetary Data System Standards Reference, ch. 7.7 "Date/Time"): UTC as
//! `YYYY-MM-DDThh:mm:ss[.fff]` or day of year `YYYY-DDDThh:mm:ss[.fff]`, an optional trailing
//! `Z`; the time part may stop after the hours or minutes, or be absent (midnight). M3 labels
//! give START_TIME and STOP_TIME this way (`2008-11-29T17:14:31`).

/// A UTC instant as a PDS3 label writes it: a calendar date and the seconds since that day's
/// midnight (60.x only within a leap second).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UtcTime {
    pub year: i32,
    pub month: u32,
    pub day: u32,
    pub seconds_of_day: f64,
}

/// Days in each month of `year` (Gregorian: a leap year is divisible by 4, except centuries
/// not divisible by 400).
fn month_lengths(year: i32) -> [u32; 12] {
    let leap = (year % 4 == 0 && year % 100 != 0) || year % 400 == 0;
    [
        31,
        if leap { 29 } else { 28 },
        31,
        30,
        31,
        30,
        31,
        31,
        30,
        31,
        30,
        31,
    ]
}

fn number<T: std::str::FromStr>(s: &str, what: &str) -> Result<T, String> {
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_digit()) {
        return Err(format!("{what} {s:?} is not a number"));
    }
    s.parse()
        .map_err(|_| format!("{what} {s:?} is not a number"))
}

impl UtcTime {
    /// Parse a PDS3 date/time (module docs). The error says which part is wrong.
    pub fn parse(text: &str) -> Result<Self, String> {
        let t = text.trim().trim_matches('"');
        let t = t.strip_suffix('Z').unwrap_or(t);
        let (date, time) = t.split_once('T').unwrap_or((t, ""));
        let parts: Vec<&str> = date.split('-').collect();
        let year: i32 = number(parts[0], "year")?;
        if parts[0].len() != 4 {
            return Err(format!("year {:?} must have four digits", parts[0]));
        }
        let lengths = month_lengths(year);
        let (month, day) = match parts[1..] {
            [m, d] => {
                let (m, d): (u32, u32) = (number(m, "month")?, number(d, "day")?);
                if !(1..=12).contains(&m) {
                    return Err(format!("month {m} is not 1–12"));
                }
                if d < 1 || d > lengths[m as usize - 1] {
                    return Err(format!("day {d} is not in month {m} of {year}"));
                }
                (m, d)
            }
            [doy] => {
                let n: u32 = number(doy, "day of year")?;
                let total: u32 = lengths.iter().sum();
                if n < 1 || n > total {
                    return Err(format!("day of year {n} is not 1–{total}"));
                }
                let (mut m, mut d) = (1, n);
                while d > lengths[m as usize - 1] {
                    d -= lengths[m as usize - 1];
                    m += 1;
                }
                (m, d)
            }
            _ => return Err(format!("date {date:?} is neither YYYY-MM-DD nor YYYY-DDD")),
        };
        let mut seconds_of_day = 0.0;
        if !time.is_empty() {
            let hms: Vec<&str> = time.split(':').collect();
            if hms.len() > 3 {
                return Err(format!("time {time:?} is not hh:mm:ss"));
            }
            let h: u32 = number(hms[0], "hour")?;
            let m: u32 = hms.get(1).map_or(Ok(0), |m| number(m, "minute"))?;
            let s: f64 = match hms.get(2) {
                None => 0.0,
                Some(s) => {
                    let (whole, frac) = s.split_once('.').unwrap_or((s, "0"));
                    number::<u32>(whole, "second")?;
                    if !frac.bytes().all(|b| b.is_ascii_digit()) {
                        return Err(format!("second {s:?} is not a number"));
                    }
                    s.parse()
                        .map_err(|_| format!("second {s:?} is not a number"))?
                }
            };
            if h > 23 || m > 59 || !(0.0..61.0).contains(&s) {
                return Err(format!("time {time:?} is out of range"));
            }
            seconds_of_day = f64::from(h * 3600 + m * 60) + s;
        }
        Ok(UtcTime {
            year,
            month,
            day,
            seconds_of_day,
        })
    }

    /// The Julian date of this instant counted in UTC (days; 2000-01-01T12:00 is 2 451 545),
    /// by the Fliegel–Van Flandern day count for the Gregorian calendar.
    pub fn julian_date(&self) -> f64 {
        let (y, m, d) = (
            i64::from(self.year),
            i64::from(self.month),
            i64::from(self.day),
        );
        let a = (14 - m) / 12;
        let (yy, mm) = (y + 4800 - a, m + 12 * a - 3);
        let jdn = d + (153 * mm + 2) / 5 + 365 * yy + yy / 4 - yy / 100 + yy / 400 - 32045;
        jdn as f64 - 0.5 + self.seconds_of_day / 86_400.0
    }
}

impl std::fmt::Display for UtcTime {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = self.seconds_of_day;
        let (h, m) = ((s / 3600.0).floor(), ((s % 3600.0) / 60.0).floor());
        write!(
            f,
            "{:04}-{:02}-{:02}T{:02}:{:02}:{:06.3}",
            self.year,
            self.month,
            self.day,
            h,
            m,
            s - h * 3600.0 - m * 60.0
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calendar_and_day_of_year_forms_agree() {
        let a = UtcTime::parse("2009-06-30T08:34:07").unwrap();
        // 2009 is not a leap year: 31+28+31+30+31 = 151 days before June, so June 30 is 181.
        let b = UtcTime::parse("2009-181T08:34:07Z").unwrap();
        assert_eq!(a, b);
        assert_eq!(a.seconds_of_day, 8.0 * 3600.0 + 34.0 * 60.0 + 7.0);
        let c = UtcTime::parse("2008-366").unwrap();
        assert_eq!((c.month, c.day, c.seconds_of_day), (12, 31, 0.0));
        let d = UtcTime::parse("\"2008-11-29T17:14:29.780687\"").unwrap();
        assert!((d.seconds_of_day - 62_069.780_687).abs() < 1e-9);
        assert_eq!(d.to_string(), "2008-11-29T17:14:29.781");
    }

    #[test]
    fn julian_dates_of_known_epochs() {
        // J2000.0 is 2000-01-01T12:00 (JD 2 451 545.0); the Unix epoch 1970-01-01T00:00 is
        // JD 2 440 587.5; 1858-11-17T00:00 is the origin of the Modified Julian Date (2 400 000.5).
        for (t, jd) in [
            ("2000-01-01T12:00:00", 2_451_545.0),
            ("1970-01-01T00:00", 2_440_587.5),
            ("1858-11-17", 2_400_000.5),
            ("2000-03-01T00", 2_451_604.5),
        ] {
            assert_eq!(UtcTime::parse(t).unwrap().julian_date(), jd, "{t}");
        }
    }

    #[test]
    fn malformed_times_say_which_part_is_wrong() {
        for (t, says) in [
            ("2009-13-01T00:00:00", "month 13"),
            ("2009-02-29T00:00:00", "day 29"),
            ("2009-366", "day of year 366"),
            ("09-06-30T08:34:07", "four digits"),
            ("2009-06-30T25:00:00", "out of range"),
            ("2009-06-30T08:34:0x", "second"),
            ("N/A", "year"),
            ("2009/06/30", "year"),
        ] {
            let e = UtcTime::parse(t).unwrap_err();
            assert!(e.contains(says), "{t}: {e}");
        }
    }
}
