//! `[[drives]]` on RTU lines and gateways: the transport, the serial line's settings and unit ids, and what a line
//! can carry.

use super::*;
use crate::modbus::line::{MAX_LINE_LOAD, Parity, line_load};

/// The drives on each RTU line: one setting per line, and no more traffic than the line can carry.
pub(super) fn check_lines(drives: &[DriveSettings]) -> Result<(), Invalid> {
    let mut lines: Vec<(Endpoint, Vec<usize>)> = Vec::new();
    for (i, d) in drives.iter().enumerate() {
        let Some((endpoint, _)) = d.line() else { continue };
        match lines.iter_mut().find(|(e, _)| e.same_line(&endpoint)) {
            Some((_, members)) => members.push(i),
            None => lines.push((endpoint, vec![i])),
        }
    }
    let line_key = |i: usize| match drives[i].transport {
        Transport::Rtu { .. } => format!("drives[{i}].serial_port"),
        _ => format!("drives[{i}].address"),
    };
    let describe =
        |l: &SerialLine| format!("{} baud, parity {}, {} stop bit(s)", l.baud_rate, l.parity.name(), l.stop_bits);
    for (endpoint, members) in &lines {
        let first = &drives[members[0]];
        let Some((_, line)) = first.line() else { continue };
        for &i in &members[1..] {
            if let Some((_, other)) = drives[i].line()
                && other != line
            {
                return Err(KeyError::new(
                    line_key(i),
                    format!(
                        "drive {:?} is on {} with {}, but drive {:?} on the same line has {}: a line has one \
                         setting",
                        drives[i].name,
                        endpoint.name(),
                        describe(&other),
                        first.name,
                        describe(&line)
                    ),
                ));
            }
        }
        let each: Vec<(Vec<(usize, usize)>, Duration)> =
            members.iter().map(|&i| (drives[i].cycle_frames(), drives[i].poll)).collect();
        let load = line_load(&line, &each);
        if load > MAX_LINE_LOAD {
            let names: Vec<String> = members
                .iter()
                .zip(&each)
                .map(|(&i, one)| {
                    format!(
                        "{:?} (poll_ms {}: {:.0} %)",
                        drives[i].name,
                        drives[i].poll.as_millis(),
                        100.0 * line_load(&line, std::slice::from_ref(one))
                    )
                })
                .collect();
            return Err(KeyError::new(
                line_key(members[members.len() - 1]),
                format!(
                    "the line {} ({}) cannot carry drives {}: together they need {:.0} % of its time, at most {:.0} % \
                     is allowed; poll less often (poll_ms), raise baud_rate, or move drives to another line",
                    endpoint.name(),
                    describe(&line),
                    names.join(", "),
                    100.0 * load,
                    100.0 * MAX_LINE_LOAD
                ),
            ));
        }
    }
    Ok(())
}

/// The transport keys of a drive, validated: `(transport, address)`, where the address is the serial port for rtu.
pub(super) fn validate_transport(d: &RawDrive, key: &dyn Fn(&str) -> String) -> Result<(Transport, String), Invalid> {
    let kind = d.transport.as_deref().unwrap_or("tcp");
    let serial_given = [
        ("serial_port", d.serial_port.is_some()),
        ("baud_rate", d.baud_rate.is_some()),
        ("parity", d.parity.is_some()),
        ("stop_bits", d.stop_bits.is_some()),
    ];
    let host_port = |address: &Option<String>| host_port(address.as_deref(), kind, key);
    let line = || serial_line(d, key);
    let rtu_unit = || rtu_unit(d.unit_id, key);
    match kind {
        "tcp" => {
            if let Some((k, _)) = serial_given.iter().find(|(_, given)| *given) {
                return Err(KeyError::new(
                    key(k),
                    "is for transport = \"rtu\" or \"rtu-over-tcp\"; this drive is on tcp".into(),
                ));
            }
            Ok((Transport::Tcp, host_port(&d.address)?))
        }
        "rtu" => {
            if d.address.is_some() {
                return Err(KeyError::new(
                    key("address"),
                    "is for tcp and rtu-over-tcp; an rtu drive is reached on serial_port".into(),
                ));
            }
            let Some(port) = d.serial_port.clone().filter(|p| !p.is_empty()) else {
                return Err(KeyError::new(
                    key("serial_port"),
                    "is required with transport = \"rtu\" (e.g. /dev/ttyUSB0)".into(),
                ));
            };
            let line = line()?;
            rtu_unit()?;
            Ok((Transport::Rtu { serial_port: port.clone(), line }, port))
        }
        "rtu-over-tcp" => {
            if d.serial_port.is_some() {
                return Err(KeyError::new(
                    key("serial_port"),
                    "is for transport = \"rtu\"; an rtu-over-tcp drive is reached at address (the gateway)".into(),
                ));
            }
            let address = host_port(&d.address)?;
            let line = line()?;
            rtu_unit()?;
            Ok((Transport::RtuOverTcp { line }, address))
        }
        other => {
            Err(KeyError::new(key("transport"), format!("{other:?}: expected \"tcp\", \"rtu\" or \"rtu-over-tcp\"")))
        }
    }
}

/// A drive's `address` as `host:port` (required with `kind`, a transport that reaches it over TCP).
pub(super) fn host_port(address: Option<&str>, kind: &str, key: &dyn Fn(&str) -> String) -> Result<String, Invalid> {
    match address {
        None => Err(KeyError::new(key("address"), format!("is required with transport = {kind:?} (host:port)"))),
        Some(a) => match a.rsplit_once(':') {
            Some((host, port)) if !host.is_empty() && port.parse::<u16>().is_ok_and(|p| p != 0) => Ok(a.to_string()),
            _ => Err(KeyError::new(
                key("address"),
                format!("{a:?} is not host:port (port 1 ..= 65535) such as 127.0.0.1:5020"),
            )),
        },
    }
}

/// A drive's serial line settings, defaults where not given.
pub(super) fn serial_line(d: &RawDrive, key: &dyn Fn(&str) -> String) -> Result<SerialLine, Invalid> {
    let mut line = SerialLine::default();
    if let Some(b) = d.baud_rate {
        if b <= 0 {
            return Err(KeyError::new(key("baud_rate"), format!("must be positive, got {b}")));
        }
        line.baud_rate = u32::try_from(b)
            .map_err(|_| KeyError::new(key("baud_rate"), format!("must be at most {}, got {b}", u32::MAX)))?;
    }
    if let Some(p) = &d.parity {
        line.parity = Parity::parse(p)
            .ok_or_else(|| KeyError::new(key("parity"), format!("{p:?}: expected \"none\", \"even\" or \"odd\"")))?;
    }
    if let Some(s) = d.stop_bits {
        if !(1..=2).contains(&s) {
            return Err(KeyError::new(key("stop_bits"), format!("must be 1 or 2, got {s}")));
        }
        line.stop_bits = s as u8;
    }
    Ok(line)
}

/// A unit id an RTU line can address (0 is broadcast).
pub(super) fn rtu_unit(unit_id: u8, key: &dyn Fn(&str) -> String) -> Result<(), Invalid> {
    if (1..=247).contains(&unit_id) {
        Ok(())
    } else {
        Err(KeyError::new(key("unit_id"), format!("must be 1 ..= 247 on an RTU line (0 is broadcast), got {unit_id}")))
    }
}
